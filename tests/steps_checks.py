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
    "instantaneous steps, 5 s pauses, 20 Hz (each pause a whole number of samples)": "step_move_s=0,dt_s=0.05",
    "instantaneous steps, 5 s pauses, 5 Hz": "step_move_s=0,dt_s=0.2",
    "instantaneous steps, 5 s pauses, 2 Hz, 6 samples a step": "step_move_s=0,dt_s=0.5,step_samples=6,rotation_samples=1000",
    "continuous recording (no pauses), instantaneous steps": "continuous=true,step_move_s=0",
    "the default plan: the logger also paused during the 1 s step moves": "",
    "continuous recording, 1 s step moves (slow moves, issue 5)": "continuous=true",
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


LOST_PACKETS = "gap_count=3,gap_s=2"


def check_lost_packets(scenario: str, seed: int, work: Path) -> tuple[int, int, int, int]:
    """The scenario's recording with packets lost at random (``LOST_PACKETS``):
    the lost runs inside a plan segment (on one step of a static sequence)
    and between segments by the simulator's labels, the gaps rotcal reports
    as missing samples, and the pauses it reports beyond the plan's own."""
    spec = SimulationSpec().with_plan(SCENARIOS[scenario]).with_timebase(LOST_PACKETS)
    sim = simulate(spec, seed)
    s = sim.samples
    interval = np.diff(s["t_ns"].to_numpy())
    longer = interval > spec.timebase.gap_s * 1e9 + 2 * spec.plan.dt_s * 1e9  # the plan's pauses (a lost run beside one joins it)
    lost = np.flatnonzero((interval > 5.5 * spec.plan.dt_s * 1e9) & ~longer)
    segment = s["plan_segment"].fill_null(-1).to_numpy()
    step = s["angle_deg"].fill_null(np.nan).to_numpy()
    static = s["rate_hz"].fill_null(0.0).to_numpy() == 0
    inside = (segment[lost] == segment[lost + 1]) & (segment[lost] >= 0) & (~static[lost] | (step[lost] == step[lost + 1]))
    data = write_dataset(sim, spec, work / f"lost{seed}", "csv-unlabelled")
    run_dataset(data, work / f"lost{seed}_out", config=RunConfig(run=RunSection(workers=1)))
    found = {r["check"]: r for r in pl.read_parquet(work / f"lost{seed}_out" / "timebase.parquet").iter_rows(named=True)}
    n_gaps = int(found["gaps"]["evidence"].split(" runs")[0])
    return int(inside.sum()), int((~inside).sum()), n_gaps, int(found["logging_pauses"]["value"]) - int(longer.sum())
