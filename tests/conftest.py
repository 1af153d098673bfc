"""Shared test fixtures: seeded simulated datasets (cached per session), the
command line run in-process, and the markers ``slow`` (run with
ROTCAL_SLOW=1) and ``real`` (skipped when the real recordings are absent)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

from rotcal.simulate import SimulationSpec, simulate, write_dataset

from testdata import REAL


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


def pytest_collection_modifyitems(items):
    """``@pytest.mark.slow`` tests run only with ROTCAL_SLOW=1;
    ``@pytest.mark.real`` tests only where the real recordings are."""
    skips = {}
    if os.environ.get("ROTCAL_SLOW") != "1":
        skips["slow"] = pytest.mark.skip(reason="long statistical run: set ROTCAL_SLOW=1")
    if not REAL.is_dir():
        skips["real"] = pytest.mark.skip(reason=f"{REAL} not found: real recordings absent (set ROTCAL_SHARED)")
    for item in items:
        for name, skip in skips.items():
            if name in item.keywords:
                item.add_marker(skip)
