"""Blind segmentation of recordings with only t, u, v, w (issue 5)."""

import numpy as np
import pytest

from rotcal.ingest.dataset import load_dataset
from rotcal.segment.blind import axis_from_normal, rough_calibration, segment_blind
from rotcal.simulate import Plan, SimulationSpec, simulate

from testdata import REAL, REPO


def _arrays(sim):
    return sim.samples["t_ns"].to_numpy(), sim.samples.select("u", "v", "w").to_numpy().astype(float)


def _truth(sim, kind):
    return [p for p in sim.truth["timeline"] if p["kind"] == kind]


def test_continuous_plan_segments_axes_and_rates():
    """Every rotation with its axis and rate, every step and rest as a dwell,
    the steps grouped into one sequence per axis; boundaries within 1 s."""
    sim = simulate(SimulationSpec(plan=Plan(continuous=True)), 11)
    t, y = _arrays(sim)
    blind = segment_blind(t, y)
    rotations = _truth(sim, "rotation")
    assert len(blind.rotations) == len(rotations)
    for r, p in zip(blind.rotations, rotations):
        assert r.axis == p["axis"] and r.axis_offset_deg < 5
        assert r.fit.rate_hz == pytest.approx(p["rate_hz"], rel=1e-5)
        assert abs(t[r.start] / 1e9 - p["t_start_s"]) < 1 and abs(t[r.stop - 1] / 1e9 - p["t_end_s"]) < 1
        assert 0.8 < r.chi2_reduced < 1.2
    rests = _truth(sim, "step") + _truth(sim, "pause")
    assert len(blind.dwells) == len(rests)
    start = np.sort([p["t_start_s"] for p in rests])
    assert np.abs(t[blind.dwells[:, 0]] / 1e9 - start).max() < 1
    assert [(q.axis, len(q.dwells)) for q in blind.sequences] == [("x", 24), ("y", 24), ("z", 24)]
    np.testing.assert_allclose(blind.noise_sd, 8.0, rtol=0.05)


def test_one_axis_recording_without_dwells_between_rates():
    """Only z, rates a decade apart; the outputs lie on one great circle, so
    the rough calibration falls back to a circle fit."""
    sim = simulate(SimulationSpec(plan=Plan(continuous=True, axes=("z",), rates_hz=(0.005, 0.02, 1.0))), 4)
    t, y = _arrays(sim)
    blind = segment_blind(t, y)
    assert [(r.axis, round(r.fit.rate_hz, 6)) for r in blind.rotations] == [("z", 0.005), ("z", 0.02), ("z", 1.0)]


def test_fast_rotation_whose_ramp_looks_steady_is_found():
    """At 2 Hz the last seconds of a 10 deg/s^2 ramp change the rate by less
    than the steady tolerance, so the candidate holds them; fitted whole, its
    quadratic phase lag failed the residual test and the rotations were
    lost without a word. The fit grows from the candidate's middle instead,
    and the edges stop where the ramp begins (167 s to 419 s on x)."""
    sim = simulate(SimulationSpec(plan=Plan(continuous=True, rates_hz=(2.0,))), 1)
    t, y = _arrays(sim)
    blind = segment_blind(t, y)
    assert [(r.axis, round(r.fit.rate_hz, 6)) for r in blind.rotations] == [("x", 2.0), ("y", 2.0), ("z", 2.0)]
    first = blind.rotations[0]
    assert abs(t[first.start] / 1e9 - 167.0) < 1.0 and abs(t[first.stop - 1] / 1e9 - 419.0) < 1.0
    assert first.chi2_reduced < 1.1


def test_rough_calibration_finds_the_offset():
    sim = simulate(SimulationSpec(plan=Plan(continuous=True)), 5)
    _, y = _arrays(sim)
    offset, to_unit = rough_calibration(y[::7])
    np.testing.assert_allclose(offset, sim.truth["dut"]["offsets"], atol=5)
    np.testing.assert_allclose(np.linalg.norm((y[::7] - offset) @ to_unit.T, axis=1).mean(), 1.0, atol=1e-3)


def test_axis_is_named_after_the_closest_channel():
    assert axis_from_normal(np.array([0.05, -0.99, 0.02]))[0] == "y"
    name, off = axis_from_normal(np.array([1.0, 1.0, 0.0]))
    assert off == pytest.approx(45.0)


@pytest.mark.real
def test_xsens_hand_placed_poses_with_no_setting_beyond_the_format():
    """Issue 5 acceptance: the real recording segments into its static poses
    (38 +- 2, the initial rest included), no rotations, no step sequences."""
    s = load_dataset(REAL / "imu_tk_xsens", REPO / "configs" / "imu_tk_xsens.toml").samples
    blind = segment_blind(s["t_ns"].to_numpy(), s.select("u", "v", "w").to_numpy().astype(float))
    assert 36 <= len(blind.dwells) <= 40
    assert not blind.rotations and not blind.sequences
    first = blind.dwells[0]
    t = s["t_ns"].to_numpy()
    assert t[first[0]] < 1e9 and 45e9 < t[first[1] - 1] < 55e9


@pytest.mark.real
def test_driving_robot_dwells_never_overlap_and_the_run_refuses_in_one_line(tmp_path):
    """The Jackal recording (a robot driving, no calibration motion): still
    intervals a few samples apart, whose dwells, each extended against its
    own mean, both reached into the samples between them (they overlapped at
    samples 2298 to 2317, and the pose table failed with a traceback). Dwells
    now tile without overlap, and the run says why it cannot calibrate."""
    from rotcal.errors import UndeterminedError
    from rotcal.run import run_dataset

    s = load_dataset(REAL / "jackal_mcap" / "test2_ros2.mcap").samples
    dwells = segment_blind(s["t_ns"].to_numpy(), s.select("u", "v", "w").to_numpy()).dwells
    assert len(dwells) == 12
    assert np.all(dwells[:, 0] < dwells[:, 1]) and np.all(dwells[1:, 0] >= dwells[:-1, 1])
    with pytest.raises(UndeterminedError, match="static poses cannot be reduced"):
        run_dataset(REAL / "jackal_mcap", tmp_path / "out")


def test_a_recording_that_never_rests_has_no_still_intervals():
    """One constant rotation: no window is quiet, so the percentile floor
    alone would call it all still; the second-difference noise floor does not."""
    from rotcal.fit.segments import design
    from rotcal.segment.stillness import still_intervals

    rng = np.random.default_rng(6)
    t_ns = np.arange(4200, dtype=np.int64) * 60_000_000
    y = design(360 * 0.5 * t_ns / 1e9) @ np.array([[300.0, 16000.0, 500.0], [-40.0, -800.0, 16300.0], [20.0, 30.0, 10.0]]).T
    assert still_intervals(t_ns, np.round(y + rng.normal(0, 8, y.shape))).height == 0


def test_rests_of_a_low_pass_filtered_sensor_are_still():
    """A sensor whose digital low-pass (second order at 0.1 of the sample
    rate) correlates its samples: second differences at lag 1 show about
    1/20 of its noise's variance, which as the floor made every one of the 30
    rests of a hand session ten times too noisy (none found before); the
    filter's memory, from where the second differences stop growing with
    the lag, gives the floor back: each rest found, none split."""
    from rotcal.segment.stillness import filter_memory_factor, still_intervals
    from rotcal.simulate.noise import NoiseSpec

    from handsim import hand_session

    noise = NoiseSpec(white_sd=8.0, lowpass_order=2, lowpass_cutoff=0.1)
    frame, _ = hand_session(100, (), noise=noise)
    t_ns = (frame["t"].to_numpy() * 1e9).round().astype(np.int64)
    y = frame.select("u", "v", "w").to_numpy()
    assert filter_memory_factor(y[:, 0], 100, 10.0) > 10.0
    assert still_intervals(t_ns, y).height == 30
    white, _ = hand_session(100, ())
    assert filter_memory_factor(white["u"].to_numpy(), 100, 10.0) == 1.0


def test_still_runs_split_at_time_gaps():
    """A gap inside a still run, and one right where a run starts, both split it."""
    from rotcal.segment.stillness import still_intervals

    t_ns = np.r_[np.arange(300), 400 + np.arange(300), 1000 + np.arange(300)].astype(np.int64) * 10_000_000
    y = np.random.default_rng(7).normal(0, 3, (900, 3)).round()
    y[300:600] += 5000.0 * np.sin(np.arange(300) / 10.0)[:, None]  # moving between the first and last gap
    out = still_intervals(t_ns, y)
    assert out.select("start", "stop").rows() == [(0, 300), (600, 900)]


@pytest.mark.parametrize("effect", [
    "centripetal:axis=x,radius_m=0.25", "cubic_nonlinearity:k3_w=1.2e-3", "quadratic_nonlinearity:k2_u=8e-4",
    "clipping:below_max=0.008", "channel_delay:delay_v_s=0.006", "rate_error:rate_error=4e-4",
    "rate_ripple:axis=y,ripple_deg=0.2", "axis_tilt:axis=z,tilt_deg=0.5", "offset_drift:drift_u=0.03",
])
def test_segmentation_survives_every_effect_at_its_large_end(effect):
    sim = simulate(SimulationSpec(plan=Plan(continuous=True)).with_effects(effect), 3)
    t, y = _arrays(sim)
    blind = segment_blind(t, y)
    rotations = _truth(sim, "rotation")
    assert [r.axis for r in blind.rotations] == [p["axis"] for p in rotations]
    factor = 1 + (4e-4 if effect.startswith("rate_error") else 0.0)
    np.testing.assert_allclose([r.fit.rate_hz for r in blind.rotations], [p["rate_hz"] * factor for p in rotations], rtol=1e-5)
    assert len(blind.dwells) == len(_truth(sim, "step") + _truth(sim, "pause"))
    assert [len(q.dwells) for q in blind.sequences] == [24, 24, 24]


def test_blocks_of_the_rate_and_the_window_variances_change_nothing(monkeypatch):
    """The angular rate and the window variances are computed block by
    block (padded by their reach) to bound memory: blocks of 500 and 64
    samples segment a continuous plan as one block does, every rotation's
    bounds and fitted rate, every dwell and the noise alike."""
    import rotcal.segment.motion as motion_module
    import rotcal.segment.stillness as stillness_module

    sim = simulate(SimulationSpec(plan=Plan(continuous=True)), 11)
    t, y = _arrays(sim)
    whole = segment_blind(t, y)
    for size in (500, 64):
        monkeypatch.setattr(motion_module, "MOTION_BLOCK", size)
        monkeypatch.setattr(stillness_module, "VARIANCE_BLOCK", size)
        blocks = segment_blind(t, y)
        assert [(r.start, r.stop, r.axis) for r in blocks.rotations] == [(r.start, r.stop, r.axis) for r in whole.rotations]
        np.testing.assert_allclose([r.fit.rate_hz for r in blocks.rotations], [r.fit.rate_hz for r in whole.rotations], rtol=1e-12)
        np.testing.assert_array_equal(blocks.dwells, whole.dwells)
        np.testing.assert_allclose(blocks.noise_sd, whole.noise_sd, rtol=1e-12)
