"""Segment fits' uncertainties with noise correlated from sample to sample
(rotcal.fit.correlated), checked by repeated simulation against the truth.

White noise of 8 counts plus a first-order autoregression (a sensor whose
filter or bias correlates successive samples): the fits' white-noise
covariance understated the spread of the coefficients 1.6 to 2.7 times."""

import numpy as np
import pytest
from scipy.signal import lfilter

from rotcal.config import FitConfig
from rotcal.fit.normal import ResidualSums
from rotcal.fit.segments import angle_step, fit_segment, widened

N, DT = 4200, 0.06
TRUTH = np.array([[100.0, 16000.0, -300.0], [-50.0, 200.0, 16000.0], [400.0, -100.0, 50.0]])


def _normalised_errors(phi: float, sd_ar: float, rate_hz: float, reps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(errors over the widened standard uncertainties, over the white-noise
    ones), reps x 9, of a rotation segment's three-parameter fits."""
    rng = np.random.default_rng(seed)
    theta = 360 * rate_hz * DT * np.arange(N) + 17.0
    x = np.column_stack([np.ones(N), np.sin(np.radians(theta)), np.cos(np.radians(theta))])
    step = angle_step(rate_hz, 0, round((N - 1) * DT * 1e9), N)
    widened_z, white_z = [], []
    for _ in range(reps):
        ar = lfilter([1.0], [1.0, -phi], rng.normal(0, sd_ar * np.sqrt(1 - phi**2), (3, N + 200)), axis=1)[:, 200:]
        y = x @ TRUTH.T + ar.T + rng.normal(0, 8.0, (N, 3))
        fit = fit_segment(0, "rotation", rate_hz, "commanded", theta, y, FitConfig())
        error = (fit.coef - TRUTH).ravel()
        widened_z.append(error / np.sqrt(np.diag(widened(fit, step).cov)))
        white_z.append(error / np.sqrt(np.diag(fit.cov)))
    return np.array(widened_z), np.array(white_z)


@pytest.mark.parametrize(("phi", "sd_ar", "rate_hz", "within"), [(0.6, 10.0, 0.05, 0.15), (0.6, 10.0, 0.5, 0.15),
                                                                (0.9, 6.0, 0.5, 0.2)])
def test_widened_uncertainties_cover_correlated_noise(phi, sd_ar, rate_hz, within):
    """300 segments: each coefficient's normalised errors have sd within
    ``within`` of 1 (the sd of such an sd is 0.04): 0.89 to 1.08 for phi
    0.6; for phi 0.9 (ten samples' correlation) up to 1.16, the estimated
    autocorrelations being noisier there. With the white-noise covariance
    they were 1.5 to 1.7 (phi 0.6) and up to 2.7 (phi 0.9, the offsets)."""
    widened_z, white_z = _normalised_errors(phi, sd_ar, rate_hz, 300, seed=5)
    assert np.all(np.abs(widened_z.std(axis=0) - 1) < within), widened_z.std(axis=0)
    assert white_z.std(axis=0).min() > 1.35


def test_white_noise_leaves_the_fits_as_they_were():
    """sd_ar 0: the lag-1 autocorrelation is significant (4 standard errors)
    in none of 200 segments' channels, so no covariance changes."""
    widened_z, white_z = _normalised_errors(0.0, 0.0, 0.05, 200, seed=6)
    assert np.array_equal(widened_z, white_z)


def test_lag_products_add_up_across_blocks():
    """The lag-1 and lag-2 product sums of a segment walked in blocks of any
    size, single samples included, equal those of the whole (to rounding)."""
    rng = np.random.default_rng(2)
    n = 1001
    theta = rng.uniform(0, 6, n)
    s, c = np.sin(theta), np.cos(theta)
    y = [rng.normal(0, 1, n) for _ in range(3)]
    for cuts in ([n], [1, 1, 1, 500, n - 503], [2, 3, n - 5], [n - 1, 1]):
        sums, at = ResidualSums(np.zeros((3, 3))), 0
        for k in cuts:
            sums.add(s[at:at + k], c[at:at + k], [v[at:at + k] for v in y])
            at += k
        np.testing.assert_allclose(sums.lag, [v[1:] @ v[:-1] for v in y], rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(sums.lag2, [v[2:] @ v[:-2] for v in y], rtol=1e-12, atol=1e-12)


def test_pose_means_widened_for_correlated_noise():
    """600 poses of 500 samples (8 counts white noise plus an
    autoregression of lag-1 parameter 0.6 and 10 counts sd): the pose means'
    normalised errors have sd 0.96 to 1.10, within 0.15 of 1 (sd of the sd
    0.03; each pose's factor comes from its own 500 samples, and its scatter
    leaves the sd a little above 1); with the white-noise covariance 1.6 to 1.8."""
    from rotcal.fit.means import group_statistics

    rng = np.random.default_rng(8)
    poses, n = 600, 500
    ar = lfilter([1.0], [1.0, -0.6], rng.normal(0, 8.0, (3, poses * n + 200)), axis=1)[:, 200:]
    y = 1000.0 + ar.T + rng.normal(0, 8.0, (poses * n, 3))
    group = np.repeat(np.arange(poses), n)
    _, means, cov = group_statistics(y, group, poses)
    z = (means - 1000.0) / np.sqrt(np.einsum("kii->ki", cov))
    white = (means - 1000.0) / (y.reshape(poses, n, 3).std(axis=1, ddof=1) / np.sqrt(n))
    assert np.all(np.abs(z.std(axis=0) - 1) < 0.15), z.std(axis=0)
    assert white.std(axis=0).min() > 1.5
