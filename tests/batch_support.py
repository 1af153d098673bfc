"""Helpers shared by the batch tests: small simulated capture trees and
readers of what a batch run leaves in its output directory."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
from pathlib import Path

import polars as pl

from rotcal.config import BatchConfig, DiagnosisConfig, RunConfig
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

from testdata import REPO

# One rate and short segments: a dataset of 8 small CSVs.
SMALL = SimulationSpec(plan=Plan(step_samples=10, rates_hz=(0.5,), rotation_samples=200))
# Batch does not care which stages run_dataset runs; the diagnosis and its
# report take 7 times as long as the rest on a small dataset, so most batch
# tests switch it off (test_batch.py keeps one test with the defaults).
NO_DIAGNOSIS = "[diagnosis]\nenabled = false\n"
SERIAL = RunConfig(diagnosis=DiagnosisConfig(enabled=False), batch=BatchConfig(workers=1))


def config_file(directory: Path, text: str = "") -> Path:
    """A ``--config`` file without the diagnosis, plus ``text``."""
    path = directory / "batch.toml"
    path.write_text(NO_DIAGNOSIS + text)
    return path


def make_root(root: Path, seeds, spec: SimulationSpec = SMALL) -> list[str]:
    """Datasets ``lot<seed % 3>/dut<seed>`` under ``root``; returns their paths relative to it."""
    paths = []
    for seed in seeds:
        rel = f"lot{seed % 3}/dut{seed:03d}"
        write_dataset(simulate(spec, seed), spec, root / rel)
        paths.append(rel)
    return paths


def result_tables(out: Path) -> dict[str, pl.DataFrame]:
    """Every published table: ``datasets/<id>/<table>`` and ``combined/<table>/<id>``."""
    files = sorted(out.glob("datasets/*/*.parquet")) + sorted(out.glob("combined/*/*.parquet"))
    return {f.relative_to(out).as_posix(): pl.read_parquet(f) for f in files}


def assert_same_tables(a: dict[str, pl.DataFrame], b: dict[str, pl.DataFrame]) -> None:
    assert sorted(a) == sorted(b)
    for name in a:
        assert a[name].equals(b[name]), name


def manifest_rows(out: Path) -> dict[str, dict]:
    with sqlite3.connect(out / "manifest.sqlite") as db:
        db.row_factory = sqlite3.Row
        return {r["dataset_path"]: dict(r) for r in db.execute("SELECT * FROM batch_datasets")}


def assert_clean(out: Path) -> None:
    """No temporary or partial file: ``.work`` empty, every link whole, every
    stored folder referenced by a link, no temporary names anywhere."""
    assert list((out / ".work").iterdir()) == []
    live = {Path(os.readlink(out / "combined")).name}
    for link in (out / "datasets").iterdir():
        assert link.is_symlink() and link.resolve().is_dir() and not link.name.startswith("."), link
        live.add(link.resolve().parent.name)
    assert {p.name for p in (out / ".store").iterdir()} == live
    names = [p.name for p in out.rglob("*")]
    assert not [n for n in names if n.endswith(".tmp") or n.endswith("-journal") or n.endswith("-wal")], names


def run_cli(*args, timeout: float = 120, **popen) -> subprocess.CompletedProcess:
    """``rotcal`` in a subprocess of this interpreter."""
    return subprocess.run([sys.executable, "-m", "rotcal", *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO, **popen)


def summary_of(stdout: str) -> dict:
    return json.loads(stdout)
