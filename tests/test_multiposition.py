"""Orientation-free static calibration (|a| = g in every pose) against
simulated truth."""

import numpy as np
import polars as pl
import pytest

from pipeline.multiposition import PoseFailure, orientation_free, pose_table
from pipeline.physics import INTRINSIC
from pipeline.simulate import DutSpec, SimulationSpec, simulate


def _static_poses(spec, seed):
    sim = simulate(spec, seed)
    s = sim.samples.filter(pl.col("rate_hz") == 0)
    step = s.select(pl.struct("plan_segment", "angle_deg").rle_id()).to_series().to_numpy()
    starts = np.flatnonzero(np.r_[True, np.diff(step) != 0])
    stops = np.r_[starts[1:], step.size]
    return pose_table(s["t_ns"].to_numpy(), s.select("u", "v", "w").to_numpy(), starts, stops), sim.truth


def test_noise_free_poses_give_the_truth():
    poses, truth = _static_poses(SimulationSpec(dut=DutSpec(noise_std=0.0, integer_output=False)), 3)
    fit = orientation_free(poses, truth["g_local"], 0.0)
    np.testing.assert_allclose(fit.result.value, [truth["intrinsic"][p] for p in INTRINSIC], rtol=1e-9, atol=1e-7)
    np.testing.assert_allclose(fit.magnitude, truth["g_local"], rtol=1e-12)


def test_noisy_poses_within_their_uncertainty():
    z = []
    for seed in range(20, 26):
        poses, truth = _static_poses(SimulationSpec(), seed)
        fit = orientation_free(poses, truth["g_local"], truth["g_local_uncertainty"])
        z.append((fit.result.value - [truth["intrinsic"][p] for p in INTRINSIC]) / fit.result.std_uncertainty)
    z = np.concatenate(z)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.4
    assert np.abs(z).max() < 4.5


def test_refuses_too_few_or_too_alike_poses():
    poses, truth = _static_poses(SimulationSpec(), 4)
    few = orientation_free(poses.head(8), truth["g_local"], 0.0)
    assert isinstance(few, PoseFailure) and "at least" in few.reason
    # one axis only: every pose on one great circle leaves the third direction unmeasured
    alike = orientation_free(poses.head(24), truth["g_local"], 0.0)
    assert isinstance(alike, PoseFailure) and "too alike" in alike.reason
