"""Steps faster than a sample and a logger that pauses between segments
(issue 13, deliverable 3): one seed here, ten in
``scripts/steps_acceptance.py``."""

from dataclasses import replace

import numpy as np
import polars as pl
import pytest

from rotcal.errors import ConfigError
from rotcal.segment.blind import segment_blind
from rotcal.segment.stillness import still_intervals
from rotcal.simulate import SimulationSpec, simulate
from rotcal.timebase.check import check_capture

from steps_checks import ACCEPTANCE, check_steps


def test_instantaneous_steps_with_pauses_give_every_rate(tmp_path):
    """The default plan, step moves of zero time, the logger paused 5 s
    between segments, one t, u, v, w file: each axis's 24 steps are found as
    one static sequence (they used to collapse into one dwell, and the 0 Hz
    result was lost), every rate is reduced within 3u of the truth, and no
    sample is reported missing."""
    c = check_steps(ACCEPTANCE, 1, tmp_path)
    assert c.rates == (0.0, 0.01, 0.05, 0.1, 0.5)
    assert c.sequences == (24, 24, 24)
    assert c.beyond(3.0) == 0 and c.values == 45
    assert c.missing_warnings == ()
    assert c.pauses == 14  # 3 axes x 5 segments: 14 pauses between them


def _jumps(dt_s: float, levels: np.ndarray, per_level: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A recording that rests ``per_level`` samples at each row of ``levels``
    and jumps between consecutive samples, with noise of sd 8."""
    y = np.repeat(levels, per_level, axis=0) + np.random.default_rng(seed).normal(0, 8, (len(levels) * per_level, 3))
    return (np.arange(y.shape[0]) * dt_s * 1e9).astype(np.int64), y


def test_a_jump_between_two_samples_ends_a_still_interval():
    """Every window on either side of a jump is quiet and every window
    across it is not: the still intervals end exactly at each jump."""
    levels = np.array([[0.0, 0.0, 1669.0], [400.0, 0.0, 1600.0], [800.0, 0.0, 1400.0]])
    t, y = _jumps(0.06, levels, 50)
    out = still_intervals(t, y)
    assert out.select("start", "stop").rows() == [(0, 50), (50, 100), (100, 150)]
    np.testing.assert_allclose(out.select("mean_u", "mean_v", "mean_w").to_numpy(), levels, atol=5)


def test_steps_on_one_circle_form_a_sequence_only_without_a_time_gap():
    """Dwells on one great circle joined by jumps form a step sequence about
    that axis; the same dwells with the logger paused between them (no move
    seen, a hand could have turned the DUT) stay single poses."""
    angle = np.deg2rad(np.arange(0.0, 360.0, 30.0))
    levels = 1669.0 * np.column_stack([np.zeros_like(angle), np.sin(angle), np.cos(angle)])  # about x
    t, y = _jumps(0.06, levels, 50)
    blind = segment_blind(t, y)
    assert len(blind.dwells) == 12
    assert [(q.axis, len(q.dwells)) for q in blind.sequences] == [("x", 12)]
    paused = t + np.repeat(np.arange(12), 50) * 2_000_000_000  # 2 s pause before each step
    assert segment_blind(paused, y).sequences == ()


def test_gaps_between_segments_are_pauses_and_gaps_inside_stay_missing(tmp_path):
    """At 20 Hz a 5 s pause is a whole number of periods, so the grid's phase
    holds: before the segments are known every pause is missing samples; once
    they are, the 14 between segments are pauses, and a packet lost inside a
    rotation is still missing samples."""
    from rotcal.run import run_dataset
    from rotcal.simulate import write_dataset

    spec = SimulationSpec().with_plan("step_move_s=0,dt_s=0.05")
    sim = simulate(spec, 2)
    rotation = sim.samples.filter(pl.col("rate_hz") == 0.1).head(2000)
    lost = rotation["t_ns"][1000:1040]  # 2 s lost in the middle of x's 0.1 Hz rotation
    sim = replace(sim, samples=sim.samples.filter(~pl.col("t_ns").is_in(lost.implode())))
    t = sim.samples["t_ns"].to_numpy()
    before = check_capture(t, [sim.samples[c].to_numpy() for c in "uvw"], "c")
    assert {f.check: f.value for f in before.findings}["missing_samples"] == 14 * 99 + 40
    data = write_dataset(sim, spec, tmp_path / "d", "csv-unlabelled")
    outcome = run_dataset(data, tmp_path / "out")
    found = {r["check"]: r for r in pl.read_parquet(tmp_path / "out" / "timebase.parquet").iter_rows(named=True)}
    assert found["missing_samples"]["value"] == 40 and found["gaps"]["value"] == pytest.approx(2.0)
    assert found["logging_pauses"]["value"] == 14 and "14 gaps between segments" in found["logging_pauses"]["evidence"]
    assert [w for w in outcome.warnings if "missing" in w] == ["recording.csv: 40 samples missing (0.0741 %), 1 gaps, longest 2 s"]


def test_plan_numbers_from_the_command_line_form():
    spec = SimulationSpec().with_plan("step_move_s=0, dt_s=0.05,continuous=true,step_samples=20")
    assert (spec.plan.step_move_s, spec.plan.dt_s, spec.plan.continuous, spec.plan.step_samples) == (0.0, 0.05, True, 20)
    for bad, message in [("dt_s=0", "dt_s = 0.0 must be a number > 0"), ("rates_hz=1", "not key=value with a key of"),
                         ("continuous=yes", "is not true or false"), ("step_samples=2.5", "is not a number")]:
        with pytest.raises(ConfigError, match=message):
            SimulationSpec().with_plan(bad)
