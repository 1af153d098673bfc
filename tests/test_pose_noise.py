"""Static poses under coloured noise: seeded sessions of hand-placed poses
of random orientation (``posesim``: 24 poses of 30 s at 0.06 s, the noise
drawn over the whole session), and the labelled model's offsets'
normalised errors z = (estimate - truth) / u over the sessions: a random
walk or a slow Gauss-Markov wander, which moves every pose's mean alike
(the offsets' wander), must be in u, and a
strong sample-to-sample correlation (AR(1) at 0.9) must not widen u
beyond the noise's own (its model, not the lag-1/lag-2 widening)."""

from __future__ import annotations

import numpy as np
import pytest

from rotcal.combine.refmodels import choose_reference_model
from rotcal.fit.means import pose_table
from rotcal.model.results import Failure
from rotcal.simulate.noise import NoiseSpec, draw_channels

from posesim import G_LOCAL, hand_placed, pose_bounds

DT_S = 0.06
SESSIONS = 16


def _offset_z(noise: NoiseSpec, seed: int) -> np.ndarray:
    clean = hand_placed(seed, samples=500, noise=0.0, move_samples=100, dt_s=DT_S, integer=False)
    y = clean.y + draw_channels(noise, len(clean.y), 1 / DT_S, np.random.default_rng([seed, 0x505]), 3)
    starts, stops = pose_bounds(clean)
    poses = pose_table(clean.t_ns, y, starts, stops).with_columns(
        ref_x=clean.directions[:, 0], ref_y=clean.directions[:, 1], ref_z=clean.directions[:, 2])
    choice = choose_reference_model(poses, G_LOCAL, 0.0)
    assert not isinstance(choice, Failure) and not isinstance(choice.full, Failure)
    result = choice.full.result
    return ((result.value - clean.truth) / result.std_uncertainty)[6:]


@pytest.mark.parametrize("noise, low, high", [
    # old code (lag-1/lag-2 widening, poses independent): z sd 4.8 (random walk), 0.6 (AR 0.9)
    (NoiseSpec(white_sd=8.0, random_walk_k=0.05), 0.7, 1.4),
    (NoiseSpec(white_sd=8.0, gauss_markov=((300.0, 3.0),)), 0.7, 1.4),
    (NoiseSpec(white_sd=8.0, ar=(0.9,), ar_sd=8.0), 0.7, 1.4),
])
def test_labelled_offsets_cover_the_pose_noise(noise, low, high):
    z = np.concatenate([_offset_z(noise, seed) for seed in range(SESSIONS)])
    assert low <= np.sqrt(np.mean(z**2)) <= high


def test_white_pose_means_carry_no_shared_part():
    clean = hand_placed(3, samples=500, noise=0.0, move_samples=100, dt_s=DT_S, integer=False)
    y = clean.y + draw_channels(NoiseSpec(white_sd=8.0), len(clean.y), 1 / DT_S, np.random.default_rng(3), 3)
    starts, stops = pose_bounds(clean)
    poses = pose_table(clean.t_ns, y, starts, stops)
    assert np.all(np.array(poses["cov_shared"][0]) == 0.0)
    own = np.array(poses["cov_mean"].to_list())[:, [0, 4, 8]]
    # white noise: the scatter's s^2 / n (8^2 / 500 counts^2) within its sampling spread
    assert np.all(np.abs(own / (64 / 500) - 1) < 0.25)
