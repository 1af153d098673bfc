"""A seeded default-plan dataset under a noise of the simulator's
``--noise`` form, through the run's stages up to the diagnosis: the
diagnosis tests under coloured noise read its findings."""

from __future__ import annotations

from pathlib import Path

from rotcal.config import RunConfig, RunSection
from rotcal.diagnose import Diagnosis
from rotcal.ingest.dataset import load_dataset
from rotcal.run.recommended import diagnose_stage
from rotcal.run.stages import determined, reduce, segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset


def diagnosis_under(noise: str, seed: int, tmp: Path, effects: str = "") -> Diagnosis:
    spec = SimulationSpec().with_noise(noise)
    if effects:
        spec = spec.with_effects(effects)
    path = write_dataset(simulate(spec, seed), spec, tmp / "d")
    ds = load_dataset(path)
    config = RunConfig(run=RunSection(workers=1))
    seg = segment_and_fit(ds, config)
    reductions = reduce(seg, ds)
    results, _, _ = determined(reductions, seg, path)
    diagnosis, _ = diagnose_stage(seg, reductions, results, ds, config)
    assert diagnosis is not None
    return diagnosis
