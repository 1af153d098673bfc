"""Checks of recordings whose table steps faster than a sample (issue 13,
deliverable 3), shared by ``tests/test_fast_steps.py`` and
``scripts/steps_acceptance.py``: the default plan simulated with the plan
numbers of a scenario (``rotcal simulate --plan``), written as one file
with ``t, u, v, w`` only, run blind, and compared with the truth."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import RunConfig, RunSection
from rotcal.model.physics import INTRINSIC
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset

# scenario -> the plan numbers (the CLI form of ``rotcal simulate --plan``)
SCENARIOS = {
    "instantaneous steps, 5 s pauses between segments": "step_move_s=0",
    "the default plan: the logger also paused during the 1 s step moves": "",
    "continuous recording, 1 s step moves (slow moves, issue 5)": "continuous=true",
    "the same at 20 Hz (each pause a whole number of samples)": "step_move_s=0,dt_s=0.05",
    "the same at 5 Hz": "step_move_s=0,dt_s=0.2",
    "the same at 2 Hz, 6 samples a step": "step_move_s=0,dt_s=0.5,step_samples=6,rotation_samples=1000",
    "continuous recording, instantaneous steps": "continuous=true,step_move_s=0",
}
ACCEPTANCE = "instantaneous steps, 5 s pauses between segments"


@dataclass(frozen=True)
class StepsChecked:
    """One seed of one scenario: the rates reduced, every (value - truth) / u
    per rate, the static sequences found (their step counts), the warnings
    about missing samples, and the logging pauses reported."""

    scenario: str
    seed: int
    rates: tuple[float, ...]
    z: dict
    sequences: tuple[int, ...]
    missing_warnings: tuple[str, ...]
    pauses: float

    def beyond(self, k: float = 3.0) -> int:
        return int(sum(np.sum(np.abs(v) > k) for v in self.z.values()))

    @property
    def values(self) -> int:
        return sum(len(v) for v in self.z.values())


def check_steps(scenario: str, seed: int, work: Path) -> StepsChecked:
    """Simulate the scenario's recording, run it from ``t, u, v, w`` alone,
    and compare with the truth."""
    spec = SimulationSpec().with_plan(SCENARIOS[scenario])
    sim = simulate(spec, seed)
    data = write_dataset(sim, spec, work / f"data{seed}", "csv-unlabelled")
    assert pl.read_csv(data / "recording.csv", n_rows=1).columns == ["t", "u", "v", "w"]
    out = work / f"out{seed}"
    outcome = run_dataset(data, out, config=RunConfig(run=RunSection(workers=1)))
    truth = {p: sim.truth["intrinsic"][p] for p in INTRINSIC}
    intrinsic = pl.read_parquet(out / "intrinsic.parquet").filter(pl.col("model") == "baseline")
    z = {rate: part.select((pl.col("value") - pl.col("parameter").replace_strict(truth)) / pl.col("std_uncertainty"))
         .to_series().to_numpy() for (rate,), part in intrinsic.group_by("rate_hz")}
    segments = pl.read_parquet(out / "segments.parquet")
    timebase = pl.read_parquet(out / "timebase.parquet")
    return StepsChecked(
        scenario, seed, tuple(sorted(z)), z,
        tuple(segments.filter(pl.col("kind") == "static").sort("t_start_ns")["n_steps"].to_list()),
        tuple(w for w in outcome.warnings if "missing" in w),
        float(timebase.filter(pl.col("check") == "logging_pauses")["value"].sum()),
    )
