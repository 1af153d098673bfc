"""A run's output directory with the ``calibration.json`` the certificate
reads, for tests (and screenshots) until the run writes the document
itself: the pipeline (``run_dataset``), then each result's entry as the
baseline model (``rate_calibration``) and the document (``Calibration``)."""

from __future__ import annotations

import dataclasses
import hashlib
from pathlib import Path

import numpy as np

from rotcal import __version__
from rotcal.config import RunConfig
from rotcal.ingest.meta import load_meta
from rotcal.model.calibration import Calibration, rate_calibration
from rotcal.run import RunOutcome, run_dataset

CREATED_UTC = "2026-11-24T00:00:00Z"  # fixed: the same run gives the same page


def _inputs(dataset: Path) -> tuple[dict, ...]:
    files = sorted(p for p in (dataset.rglob("*") if dataset.is_dir() else [dataset]) if p.is_file())
    root = dataset if dataset.is_dir() else dataset.parent
    return tuple({"path": p.relative_to(root).as_posix(), "bytes": p.stat().st_size,
                  "sha256": hashlib.sha256(p.read_bytes()).hexdigest()} for p in files)


def calibrated_run(dataset: Path, out: Path, meta: Path | None = None, config: RunConfig = RunConfig()) -> RunOutcome:
    """Run ``dataset`` into ``out`` and write ``out/calibration.json`` beside its tables."""
    outcome = run_dataset(dataset, out, meta, config)
    toml = meta or (dataset / "dataset.toml" if dataset.is_dir() else None)
    resolved = load_meta(toml if toml is not None and toml.is_file() else None)
    table_frame = outcome.static.frame if outcome.static is not None else "table"
    # the run does not say each result's frame: a responsivity matrix with a zero upper triangle is in the intrinsic one
    rates = tuple(rate_calibration(r, "intrinsic" if not np.triu(r.state[:9].reshape(3, 3), 1).any() else table_frame,
                                   "baseline", "no effect beyond the papers' model was modelled", outcome.output_unit)
                  for r in outcome.results)
    source = "dataset.toml [site]" if toml is not None and "g_local" in toml.read_text() else "standard gravity (default)"
    Calibration(outcome.dataset, {"id": resolved.device_id, "output_unit": outcome.output_unit}, outcome.output_unit,
                outcome.results[0].g_local, outcome.results[0].g_uncertainty, source, _inputs(dataset),
                dataclasses.asdict(config), __version__, CREATED_UTC, rates).write(out / "calibration.json")
    return outcome
