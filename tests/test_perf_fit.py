"""The batched three-parameter fit (``fit.sine3_fit``) against the plain
least-squares solution, and its sines against numpy's."""

import numpy as np
import pytest

from rotcal.config import FitConfig
from rotcal.fit.segments import design, fit_segment, linear_fit, residual_stats
from rotcal.fit.sines import sincos_deg, sine3_fit

RNG = np.random.default_rng(17)
TRUTH = np.array([[500.0, -120.0, 16300.0], [-30.0, -16250.0, 80.0], [12.0, 40.0, -35.0]])

ANGLES = {
    # a constant rotation sampled at a constant rate: the progression path, several blocks
    "rotation": 37.0 + 0.0605 * np.arange(30_000),
    # many turns: angles near 1e6 deg
    "many_turns": 1e6 + 0.216 * np.arange(20_000),
    # a static step sequence (Geist 2017): the table path
    "static_steps": np.repeat(np.arange(0.0, 360.0, 15.0), 50),
    # measured angles with encoder jitter: off the progression
    "jittered": 5.0 + 0.3 * np.arange(10_000) + RNG.normal(0, 1e-3, 10_000),
    # the shortest arc the fit accepts, ill-conditioned
    "short_arc": 200.0 + np.linspace(0.0, 30.0, 400),
}


@pytest.mark.parametrize("name", sorted(ANGLES))
def test_batched_fit_equals_lstsq(name):
    theta = ANGLES[name]
    y = design(theta) @ TRUTH.T + RNG.normal(0, 8, (theta.size, 3))
    coef, cov, rtr, max_abs, lag = sine3_fit(theta, tuple(y.T))
    x = design(np.fmod(theta, 360.0))  # exact range reduction: np.deg2rad of 1e6 deg is off by ~1e-11 rad
    reference = np.linalg.lstsq(x, y, rcond=None)[0].T
    scale = np.abs(reference).max(axis=1, keepdims=True)  # each channel's coefficients on their own scale
    assert np.abs(coef - reference).max() / scale.min() < 1e-9
    _, ref_cov, resid = linear_fit(x, y)
    np.testing.assert_allclose(cov, ref_cov, rtol=1e-9, atol=1e-9 * np.abs(ref_cov).max())  # on the covariance's scale
    rms, ref_max, ref_lag1, _ = residual_stats(resid)
    np.testing.assert_allclose(np.diag(rtr), np.einsum("ij,ij->j", resid, resid), rtol=1e-9)
    np.testing.assert_allclose(max_abs, ref_max, rtol=1e-9, atol=1e-11 * np.abs(y).max())
    np.testing.assert_allclose(lag / np.diag(rtr), ref_lag1, atol=1e-9)


def test_sines_by_angle_addition_match_numpy():
    theta = np.concatenate([RNG.uniform(-720, 720, 100_000), RNG.uniform(-1e6, 1e6, 100_000), [0.0, 90.0, 180.0, -270.0]])
    s, c = sincos_deg(theta)
    reduced = np.deg2rad(np.fmod(theta, 360.0))  # fmod is exact; deg2rad of 1e6 deg is not good to 1e-15
    assert np.abs(s - np.sin(reduced)).max() < 1.5e-15
    assert np.abs(c - np.cos(reduced)).max() < 1.5e-15
    assert s[-4:-2].tolist() == [0.0, 1.0] and c[-4] == 1.0


def test_noise_free_segment_is_exact():
    theta = ANGLES["rotation"]
    fit = fit_segment(0, "rotation", 0.01, "commanded", theta, design(theta) @ TRUTH.T, FitConfig())
    np.testing.assert_allclose(fit.coef, TRUTH, rtol=1e-12, atol=1e-9)
    assert fit.max_abs.max() < 1e-8
