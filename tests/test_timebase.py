"""Time-base checks and repairs against known stamps (issue 5)."""

import numpy as np
import pytest

from rotcal.errors import InputError
from rotcal.simulate import Plan, SimulationSpec, simulate
from rotcal.timebase.check import check_capture

PERIOD_NS = 60_000_000


def _grid(n: int, rng, drop: float = 0.0) -> np.ndarray:
    slots = np.flatnonzero(rng.random(n) >= drop)
    return 7_000_000_000 + slots * PERIOD_NS


def _found(tb):
    return {f.check: f for f in tb.findings}


def test_clean_stamps_are_left_alone():
    t = _grid(5000, np.random.default_rng(0))
    tb = check_capture(t, np.random.default_rng(1).normal(0, 8, (5000, 3)).T, "c")
    f = _found(tb)
    assert not any(x.detected for x in tb.findings)
    assert f["sample_interval"].value == pytest.approx(0.06, abs=1e-15)
    np.testing.assert_array_equal(tb.t_ns, t)


def test_defects_counted_exactly_and_jitter_repaired():
    """Drops, lost packets, records written twice, repeated stamps and 5 ms
    stamp jitter: every count exact, the jitter measured, and the repaired
    stamps on the true grid (to the grid fit's own precision)."""
    rng = np.random.default_rng(2)
    n = 20000
    keep = rng.random(n) >= 0.01
    keep[5000:5040] = False  # a lost packet of 40 samples
    true = (7_000_000_000 + np.arange(n) * PERIOD_NS)[keep]
    y = rng.normal(0, 8, (true.size, 3)).round()
    stamps = true + np.round(rng.normal(0, 5e6, true.size)).astype(np.int64)
    repeat = np.flatnonzero(rng.random(true.size) < 0.005)
    repeat = repeat[(repeat > 0) & ~np.isin(repeat - 1, repeat)]
    stamps[repeat] = stamps[repeat - 1]
    twice = np.sort(rng.choice(true.size, 50, replace=False))
    order = np.sort(np.r_[np.arange(true.size), twice])
    tb = check_capture(stamps[order], y[order].T, "c")
    f = _found(tb)
    assert f["duplicated_samples"].value == 50
    assert f["repeated_stamps"].value == repeat.size
    assert f["missing_samples"].value == n - keep.sum()
    assert f["gaps"].detected and f["gaps"].value == pytest.approx(40 * 0.06, rel=1e-6)
    assert f["timestamp_jitter"].detected and "refit" in f["timestamp_jitter"].action
    assert f["timestamp_jitter"].value == pytest.approx(5e-3, rel=0.05)
    assert not f["logging_pauses"].value
    # every kept sample on its true slot, to the grid fit's own precision (about 0.04 ms);
    # only samples whose slot is ambiguous (empty slots on both sides) are dropped
    assert tb.t_ns.size >= true.size - 10
    np.testing.assert_allclose(tb.t_ns, true[order[tb.keep]], rtol=0, atol=0.2e6)


def test_logging_pauses_restart_the_phase_and_are_not_missing_samples():
    t = np.r_[np.arange(100) * PERIOD_NS, 8_010_000_000 + np.arange(100) * PERIOD_NS]
    tb = check_capture(t, np.zeros((3, 200)), "c")
    f = _found(tb)
    assert f["logging_pauses"].value == 1 and not f["missing_samples"].detected


def test_stepped_clock_is_kept_as_stamped():
    """A stamp clock corrected in 1 ms steps (the Xsens recording) wanders
    smoothly about the grid: irregular, not jitter; stamps kept."""
    n = 20000
    t = (np.arange(n) * 10_000_000 - (np.arange(n) // 1000) * 1_000_000).astype(np.int64)
    tb = check_capture(t, np.zeros((3, n)), "c")
    f = _found(tb)
    assert f["irregular_sampling"].detected and not f["timestamp_jitter"].detected
    np.testing.assert_array_equal(tb.t_ns, t)


def test_irregular_sampling_keeps_stamps_and_drops_unplaceable_repeats():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.normal(PERIOD_NS, 3e6, 5000)).astype(np.int64)
    t[100] = t[99]
    tb = check_capture(t, rng.normal(0, 8, (5000, 3)).T, "c")
    f = _found(tb)
    assert f["irregular_sampling"].detected and f["repeated_stamps"].value == 1
    assert tb.keep.sum() == 4999
    np.testing.assert_array_equal(tb.t_ns, np.delete(t, 100))


def test_jitter_too_large_to_place_is_marked_unrepairable():
    rng = np.random.default_rng(4)
    t = np.sort(np.arange(5000) * PERIOD_NS + np.round(rng.normal(0, 15e6, 5000)).astype(np.int64))
    tb = check_capture(t, np.zeros((3, 5000)), "c")
    assert tb.unrepairable and "too large" in tb.unrepairable


def test_stamps_that_do_not_advance_are_refused():
    with pytest.raises(InputError, match="do not advance"):
        check_capture(np.zeros(100, np.int64), np.zeros((3, 100)), "c")


def test_simulated_logger_defects_are_found_with_their_size():
    spec = SimulationSpec(plan=Plan(continuous=True)).with_timebase(
        "drop_fraction=0.01,gap_count=2,duplicate_fraction=0.005,repeat_stamp_fraction=0.005,jitter_s=0.005")
    sim = simulate(spec, 7)
    s = sim.samples.sort("t_ns", maintain_order=True)
    f = _found(check_capture(s["t_ns"].to_numpy(), [s[c].to_numpy() for c in "uvw"], "c"))
    real = sim.truth["timebase"]
    assert f["duplicated_samples"].value == real["duplicated_records"]
    assert f["repeated_stamps"].value == real["repeated_stamps"]
    assert f["missing_samples"].value == real["missing_samples"]
    assert f["timestamp_jitter"].value == pytest.approx(real["jitter_realised_s"], rel=0.03)


def test_repaired_stamps_are_the_true_sampling_instants():
    """The same simulated recording with and without stamp jitter and
    repeated stamps (the logger's random draws are the same): after repair
    every kept sample sits within 0.2 ms of its true, drift-scaled instant."""
    base = SimulationSpec(plan=Plan(continuous=True))
    noisy = simulate(base.with_timebase("drop_fraction=0.01,duplicate_fraction=0.005,repeat_stamp_fraction=0.005,"
                                        "jitter_s=0.005,clock_drift_ppm=200"), 102).samples
    clean = simulate(base.with_timebase("drop_fraction=0.01,duplicate_fraction=0.005,clock_drift_ppm=200"), 102).samples
    tb = check_capture(noisy["t_ns"].to_numpy(), [noisy[c].to_numpy() for c in "uvw"], "c")
    err = tb.t_ns - clean["t_ns"].to_numpy()[tb.keep]
    assert np.abs(err).max() < 0.2e6
    assert tb.keep.sum() > noisy.height - _found(tb)["duplicated_samples"].value - 40


@pytest.mark.parametrize("runs, per_run", [(1, 1200), (24, 50)])
def test_sample_interval_uncertainty_covers_the_true_period(runs, per_run):
    """Coverage by repeated simulation: 2 ms of stamp jitter on 60 ms
    samples, logged in ``runs`` runs of ``per_run`` samples whose grid phase
    changes at each pause (a static capture's steps). Each run has its own
    offset, so only the slots' scatter within the runs tells the period:
    counted over the whole capture, the uncertainty was some 40 times too
    small (the normalised errors' sd 42, not 1). The phase moves by a
    quarter to three quarters of a period: a restart within about 1.6 ms of
    the old grid reads as lost packets (the runs joined, as they must be
    for a logger that dropped samples), and that period is then not covered
    (sd 2.2 with phases drawn uniformly)."""
    rng = np.random.default_rng(11)
    z = []
    for _ in range(300):
        pauses = np.round(rng.uniform(4.9e9, 5.1e9, runs) / PERIOD_NS) * PERIOD_NS + rng.uniform(0.25, 0.75, runs) * PERIOD_NS
        starts = np.cumsum(pauses)  # pauses of about 5 s, the grid's phase moved
        true = (starts[:, None] + np.arange(per_run) * PERIOD_NS).ravel()
        stamps = np.round(true + rng.normal(0, 2e6, true.size)).astype(np.int64)
        f = _found(check_capture(stamps, [np.zeros(true.size)] * 3, "c"))["sample_interval"]
        z.append((f.value - PERIOD_NS / 1e9) / f.std_uncertainty)
    assert 0.85 < np.std(z) < 1.15 and abs(np.mean(z)) < 0.2, (np.std(z), np.mean(z))


def test_repair_of_a_defective_recording_is_pinned():
    """The simulated logger defects above, every figure exactly as the
    time base gave it before it was rewritten for captures of millions of
    samples (the same arithmetic, fewer sample-length arrays)."""
    spec = SimulationSpec(plan=Plan(continuous=True)).with_timebase(
        "drop_fraction=0.01,gap_count=2,duplicate_fraction=0.005,repeat_stamp_fraction=0.005,jitter_s=0.005")
    s = simulate(spec, 7).samples.sort("t_ns", maintain_order=True)
    tb = check_capture(s["t_ns"].to_numpy(), [s[c].to_numpy() for c in "uvw"], "c")
    f = _found(tb)
    # to 1e-13 (the jitter refit to 1e-9): the last bits follow the BLAS kernel the machine picks
    assert f["sample_interval"].value == pytest.approx(0.059999998698548995, rel=1e-13, abs=0)
    assert f["sample_interval"].std_uncertainty == pytest.approx(1.2577748014207093e-09, rel=1e-12, abs=0)
    assert [f[c].value for c in ("duplicated_samples", "repeated_stamps", "missing_samples")] == [280, 289, 686]
    assert f["gaps"].value == pytest.approx(1.979999957052117, rel=1e-13, abs=0)
    assert [f["timestamp_jitter"].value, f["timestamp_jitter"].std_uncertainty] == pytest.approx([0.004916774543566965, 1.4590413575394562e-05], rel=1e-9, abs=0)
    assert f["irregular_sampling"].value == pytest.approx(0.004975705677806501, rel=1e-9, abs=0)
    assert f["irregular_sampling"].evidence == ("stamps deviate from a regular grid by 4.98 ms (sd), 21.1 ms at most, "
                                                "residual lag-1 autocorrelation 0.01")
    assert "14 could not be placed" in f["repeated_stamps"].evidence
    assert (s.height, int(tb.keep.sum()), int(np.flatnonzero(~tb.keep).sum())) == (57061, 56767, 8734692)
    assert abs(int(tb.t_ns.sum()) - 97890459201920440) < 100  # a few stamps may round the other way (BLAS)


def _samples(capture: str, t_ns: np.ndarray, u: np.ndarray):
    import polars as pl

    from rotcal.tables import conform
    return conform(pl.DataFrame({"capture": capture, "t_ns": t_ns, "u": u, "v": 0.0, "w": 0.0, "axis": None, "rate_hz": None,
                                 "angle_deg": None, "temperature_c": None, "gx": None, "gy": None, "gz": None,
                                 "pose": None, "label_source": None}), "samples")


def test_repaired_table_keeps_rows_in_time_and_capture_order():
    """Two captures on one clock: a clean one comes back as it was; with a
    record written twice in the second, that row goes, and at a stamp both
    share the capture met first in the table comes first (as when each
    capture's rows were concatenated and sorted stably), whatever the order
    the rows came in."""
    import polars as pl

    from rotcal.timebase.repair import repair_timebase
    a = _samples("a.csv", 1_000_000_000 + np.arange(400) * PERIOD_NS, np.arange(400.0))
    assert repair_timebase(a, "ds").samples.equals(a)
    b_t = 1_000_000_000 + 200 * PERIOD_NS + np.arange(300) * PERIOD_NS
    b_t = np.insert(b_t, 10, b_t[9])  # written twice
    b = _samples("b.csv", b_t, np.insert(-np.arange(300.0), 10, -9.0))
    both = pl.concat([b, a]).sort("t_ns", maintain_order=True)
    out = repair_timebase(both, "ds")
    assert out.samples.height == 700
    assert out.samples["t_ns"].is_sorted()
    shared = out.samples.filter(pl.col("t_ns") == 1_000_000_000 + 200 * PERIOD_NS)
    assert both.filter(pl.col("t_ns") == shared["t_ns"][0])["capture"].to_list() == ["b.csv", "a.csv"]
    assert shared["capture"].to_list() == ["a.csv", "b.csv"]
    assert out.findings.filter(pl.col("check") == "duplicated_samples").select("capture", "value").rows() == [("a.csv", 0.0), ("b.csv", 1.0)]


def test_captures_one_after_another_are_repaired_each_on_its_own_rows():
    """Captures whose rows follow one another (as ingest reads files) are
    checked as runs of the table: a record written twice in the second is
    dropped and its jittered stamps are replaced by its fitted grid, exactly
    as when that capture is checked alone, and the first keeps its rows."""
    import polars as pl

    from rotcal.timebase.repair import repair_timebase
    a_t = 1_000_000_000 + np.arange(400) * PERIOD_NS
    b_grid = a_t[-1] + 50 * PERIOD_NS + np.arange(500) * PERIOD_NS
    b_t = b_grid + np.rint(np.random.default_rng(5).normal(0, 0.01 * PERIOD_NS, 500)).astype(np.int64)
    b_t, b_u = np.insert(b_t, 10, b_t[9]), np.insert(-np.arange(500.0), 10, -9.0)  # record 9 written twice
    both = pl.concat([_samples("a.csv", a_t, np.arange(400.0)), _samples("b.csv", b_t, b_u)])
    out = repair_timebase(both, "ds").samples
    alone = check_capture(b_t, [b_u, np.zeros(b_u.size), np.zeros(b_u.size)], "b.csv")
    assert out.height == 900 and int(alone.keep.sum()) == 500
    np.testing.assert_array_equal(out["t_ns"].to_numpy()[:400], a_t)
    np.testing.assert_array_equal(out["t_ns"].to_numpy()[400:], alone.t_ns)
    np.testing.assert_array_equal(out["u"].to_numpy()[400:], -np.arange(500.0))
    assert np.ptp(np.diff(alone.t_ns)) <= 1 < np.ptp(np.diff(b_t[np.r_[0:10, 11:501]]))  # refit: on a regular grid


def test_jitter_never_stamps_a_sample_before_the_logger_starts(cli, tmp_path):
    """Stamp jitter larger than the first samples' times would give negative
    stamps, which an MCAP log time cannot hold (rotcal simulate stopped with
    struct.error); the logger's clock starts at 0."""
    spec = SimulationSpec().with_timebase("jitter_s=0.1")
    stamps = simulate(spec, 1).samples["t_ns"].to_numpy()
    assert stamps.min() == 0
    code, _, err = cli("simulate", tmp_path / "d", "--format", "mcap-json", "--timebase", "jitter_s=0.1")
    assert code == 0, err


def test_median_is_numpys_for_odd_and_even_counts_and_ties():
    """``grid.median`` gives np.median's value bit for bit (the mean of the
    two middle values for an even count), and 2.5 for 1, 2, 3, 4 by hand."""
    from rotcal.timebase.grid import median

    assert median(np.array([4.0, 1.0, 3.0, 2.0])) == 2.5
    rng = np.random.default_rng(5)
    for n in (1, 2, 7, 3600, 3601):
        x = rng.normal(size=n).round(1)  # ties
        assert median(x.copy()) == np.median(x)
