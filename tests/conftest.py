"""Shared test fixtures: seeded simulated datasets (cached per session) and
the real recordings in ../shared/data/real, read in place."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import pytest

from rotcal.simulate.core import SimulationSpec, simulate, write_dataset

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ROTCAL_SHARED", REPO.parent / "shared"))
REAL = SHARED / "data" / "real"


@pytest.fixture(scope="session")
def make_dataset(tmp_path_factory):
    """``make_dataset(seed, fmt="csv", effects=(), spec=None)`` -> dataset dir.

    The same arguments give the same directory within a session.
    """
    cache: dict = {}

    def make(seed: int, fmt: str = "csv", effects: tuple[str, ...] = (), spec: SimulationSpec | None = None) -> Path:
        key = (seed, fmt, effects, repr(spec))
        if key not in cache:
            base = spec or SimulationSpec()
            full = base.with_effects(*effects)
            directory = tmp_path_factory.mktemp(f"ds{seed}_{fmt}")
            cache[key] = write_dataset(simulate(full, seed), full, directory, fmt)
        return cache[key]

    return make


def truth_of(dataset: Path) -> dict:
    return json.loads((dataset / "truth.json").read_text())


@pytest.fixture
def cli(monkeypatch, capsys):
    """Run the ``rotcal`` entry point in-process: returns (exit code, stdout, stderr)."""
    from rotcal.cli import main

    def invoke(*args: str) -> tuple[int, str, str]:
        monkeypatch.setattr(sys, "argv", ["rotcal", *map(str, args)])
        monkeypatch.setenv("COLUMNS", "200")
        try:
            main()
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        captured = capsys.readouterr()
        return code, captured.out, captured.err

    return invoke


def pytest_collection_modifyitems(config, items):
    """``@pytest.mark.slow`` tests run only with ROTCAL_SLOW=1."""
    if os.environ.get("ROTCAL_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="long statistical run: set ROTCAL_SLOW=1")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)
