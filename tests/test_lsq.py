"""Least squares with noise and excess scatter (lsq.ols) against closed forms
and repeated simulation."""

import numpy as np
import pytest

from rotcal.errors import UndeterminedError
from rotcal.fit.lsq import excess_is_significant, nonlinear, ols, psd_part


def _design(rng, n):
    return np.column_stack([rng.normal(0, 3000, (n, 3)), np.ones(n)])


def test_estimate_is_least_squares_and_classical_covariance_without_noise():
    rng = np.random.default_rng(0)
    x = _design(rng, 12)
    y = x @ rng.normal(0, 1e-4, (4, 2)) + rng.normal(0, 1e-3, (12, 2))
    fit = ols(x, y)
    np.testing.assert_allclose(fit.coef, np.linalg.lstsq(x, y, rcond=None)[0], rtol=1e-10)
    s2 = fit.sum_sq_residual / fit.dof
    xtx_inv = np.linalg.inv(x.T @ x)
    np.testing.assert_allclose(fit.cov[:4, :4], s2[0] * xtx_inv, rtol=1e-9)
    np.testing.assert_allclose(fit.cov[4:, 4:], s2[1] * xtx_inv, rtol=1e-9)


def test_exact_fit_without_noise_has_undetermined_covariance():
    rng = np.random.default_rng(1)
    x = _design(rng, 4)
    fit = ols(x, rng.normal(size=4))
    assert fit.dof == 0 and np.all(np.isnan(fit.cov))
    assert np.all(np.isfinite(ols(x, rng.normal(size=4), np.full((4, 1, 1), 1e-6)).cov))


def test_refuses_a_design_that_does_not_determine_the_coefficients():
    x = np.column_stack([np.arange(6.0), 2 * np.arange(6.0), np.ones(6)])
    with pytest.raises(UndeterminedError, match="too few or too alike"):
        ols(x, np.arange(6.0))
    with pytest.raises(UndeterminedError, match="3 positions cannot determine 4"):
        ols(np.ones((3, 4)), np.ones(3))


@pytest.mark.parametrize("excess", [0.0, 3.0])
def test_covariance_matches_the_scatter_of_repeated_fits(excess):
    """Known noise that differs between observations, with and without an
    excess scatter the fit must find: the mean reported variance of each
    coefficient matches the scatter of 1200 fits. (With the excess
    estimated from 6 degrees of freedom the normalised errors follow
    Student's t, RMS sqrt(6/4); with known noise alone, RMS 1.)"""
    rng = np.random.default_rng(2)
    x = _design(rng, 10)
    truth = np.array([1.0, -0.5, 0.2, 40.0])
    sigma = rng.uniform(0.5, 2.0, 10)
    est, var = [], []
    for _ in range(1200):
        y = x @ truth + rng.normal(0, 1, 10) * np.sqrt(sigma**2 + excess**2)
        fit = ols(x, y, (sigma**2)[:, None, None])
        est.append(fit.coef[:, 0])
        var.append(np.diag(fit.cov))
    est, var = np.array(est), np.array(var)
    ratio = var.mean(axis=0) / est.var(axis=0)
    z_rms = np.sqrt(np.mean((est - truth) ** 2 / var, axis=0))
    print(f"excess {excess}: reported / observed variance {np.round(ratio, 3)}, z RMS {np.round(z_rms, 3)}")
    assert np.all((ratio > 0.85) & (ratio < 1.18)), ratio
    if excess == 0:
        assert np.all((z_rms > 0.92) & (z_rms < 1.08)), z_rms


def test_excess_significance_and_psd_part():
    assert not excess_is_significant(10.0, 10) and excess_is_significant(30.0, 10) and not excess_is_significant(5.0, 0)
    m = np.array([[2.0, 0.0], [0.0, -1.0]])
    np.testing.assert_allclose(psd_part(m), [[2.0, 0.0], [0.0, 0.0]], atol=1e-15)


def test_nonlinear_gives_the_estimate_covariance_and_dof_of_a_known_problem():
    """y = a exp(-b t) with unit-variance noise: the estimate is the least-squares
    minimum (zero gradient), its covariance (J'J)^-1 matches the scatter of
    repeated fits, the gain is d(estimate)/d(observation)."""
    t = np.linspace(0, 4, 40)
    truth = np.array([5.0, 0.7])

    def fit_of(y):
        return nonlinear(lambda p: (p[0] * np.exp(-p[1] * t) - y) / 0.1,
                         lambda p: np.column_stack([np.exp(-p[1] * t), -p[0] * t * np.exp(-p[1] * t)]) / 0.1,
                         np.array([1.0, 0.1]), 1e-12)

    rng = np.random.default_rng(3)
    fits = [fit_of(truth[0] * np.exp(-truth[1] * t) + rng.normal(0, 0.1, t.size)) for _ in range(400)]
    one = fits[0]
    assert one.converged and one.dof == 38
    np.testing.assert_allclose(one.jac.T @ one.residuals, 0.0, atol=1e-6)  # |J| |r| ~ 1e3
    np.testing.assert_allclose(one.gain @ one.jac, np.eye(2), atol=1e-10)
    np.testing.assert_allclose(one.cov, one.gain @ one.gain.T, rtol=1e-10)
    scatter = np.cov(np.array([f.x for f in fits]).T)
    np.testing.assert_allclose(np.sqrt(np.diag(scatter)), np.sqrt(np.diag(one.cov)), rtol=0.15)
    assert np.mean([f.chi2 for f in fits]) == pytest.approx(38, rel=0.05)


def test_a_shared_solution_gives_the_same_fit_bit_for_bit_and_the_exact_line():
    """``ols`` with the design's ``least_squares_solution`` passed in is the
    fit it computes itself; on y = 2 + 3 t exactly the coefficients are (2, 3)."""
    from rotcal.fit.lsq import least_squares_solution

    t = np.arange(6.0)
    x = np.column_stack([np.ones(6), t])
    solution = least_squares_solution(x)
    np.testing.assert_allclose(solution.coef(2 + 3 * t)[:, 0], [2.0, 3.0], rtol=1e-14)
    rng = np.random.default_rng(3)
    y = 2 + 3 * t + rng.normal(0, 0.1, 6)
    noise = np.full((6, 1, 1), 0.01)
    alone, shared = ols(x, y, noise), ols(x, y, noise, solution)
    for field in ("coef", "cov", "residuals", "excess_cov"):
        np.testing.assert_array_equal(getattr(shared, field), getattr(alone, field))
    with pytest.raises(UndeterminedError):
        least_squares_solution(np.column_stack([np.ones(6), np.ones(6)]))
