"""calibration.json for the apply and export tests: a dataset run through
the pipeline's stages (``run.segment_and_fit``, ``run.reduce``) and its
results written as the document (``rotcal.model.calibration``) holds them,
the baseline model per rate, each in the frame of its reduction
(``run.Reductions.framed``)."""

from __future__ import annotations

from pathlib import Path

from rotcal.config import RunConfig
from rotcal.ingest import load_dataset
from rotcal.model.calibration import Calibration, rate_calibration
from rotcal.run.stages import Reductions, reduce, segment_and_fit


def calibrate(dataset: Path, out: Path, meta_path: Path | None = None) -> tuple[Path, Reductions]:
    """Write ``out/calibration.json`` for ``dataset``; its path and the reductions."""
    ds = load_dataset(dataset, meta_path)
    reductions = reduce(segment_and_fit(ds, RunConfig()), ds)
    assert isinstance(reductions, Reductions)
    unit = ds.meta.output_unit
    rates = tuple(rate_calibration(result, frame, "baseline", "the papers' model (test support)", unit)
                  for result, frame in reductions.framed())
    cal = Calibration(ds.name, {"id": ds.meta.device_id}, unit, ds.meta.g_local, ds.meta.g_local_uncertainty,
                      "dataset.toml [site]", (), {}, "test", "2026-11-24T00:00:00Z", rates)
    out.mkdir(parents=True, exist_ok=True)
    return cal.write(out / "calibration.json"), reductions
