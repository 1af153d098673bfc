"""The four-parameter sine fit against closed-form truth and repeated
simulation (rate and coefficient uncertainties are honest)."""

import numpy as np
import pytest

from rotcal.fit.segments import design
from rotcal.fit.sinefit import fit_sine, spectral_rate

TRUTH = np.array([[500.0, -1200.0, 16300.0], [-30.0, -16250.0, 800.0], [12.0, 400.0, -350.0]])


def _segment(rate_hz: float, theta0_deg: float, n: int = 4200, dt_ns: int = 60_000_000):
    t_ns = 123_000_000_000 + np.arange(n, dtype=np.int64) * dt_ns
    return t_ns, design(theta0_deg + 360 * rate_hz * (t_ns - t_ns[0]) / 1e9) @ TRUTH.T


def test_noise_free_rate_and_coefficients_are_exact():
    t_ns, y = _segment(0.0512345, 77.0)
    fit = fit_sine(t_ns, y, 0.05)
    assert fit.rate_hz == pytest.approx(0.0512345, rel=1e-10)
    # against its own phase: the amplitudes and the offsets are those of the truth
    np.testing.assert_allclose(np.hypot(fit.coef[:, 1], fit.coef[:, 2]), np.hypot(TRUTH[:, 1], TRUTH[:, 2]), rtol=1e-9)
    np.testing.assert_allclose(fit.coef[:, 0], TRUTH[:, 0], atol=1e-6)
    np.testing.assert_allclose(fit.model(t_ns), y, atol=1e-4)


def test_spectral_rate_finds_the_peak_within_a_fraction_of_a_bin():
    t_ns, y = _segment(0.1, 10.0, n=1000)
    assert spectral_rate((t_ns - t_ns[0]) / 1e9, y, 0.05, 0.2) == pytest.approx(0.1, rel=2e-3)


@pytest.mark.parametrize("rate_hz", [0.01, 0.5])
def test_reported_uncertainties_match_the_scatter(rate_hz):
    """Coverage by repetition: 150 noisy fits with random starting angles."""
    rng = np.random.default_rng(5)
    rates, u_rates, amp, u_amp = [], [], [], []
    for _ in range(150):
        t_ns, y = _segment(rate_hz, rng.uniform(0, 360), n=1500)
        fit = fit_sine(t_ns, y + rng.normal(0, 8, y.shape), rate_hz * 1.05)
        rates.append(fit.rate_hz)
        u_rates.append(fit.rate_u_hz)
        # C is phase-free: its reported variance must match its scatter
        amp.append(fit.coef[:, 0])
        u_amp.append(np.sqrt(np.diag(fit.cov)[[0, 3, 6]]))
    rates = np.array(rates)
    assert abs(rates.mean() - rate_hz) < 4 * np.mean(u_rates) / np.sqrt(150)
    assert rates.std() == pytest.approx(np.mean(u_rates), rel=0.2)
    np.testing.assert_allclose(np.std(amp, axis=0), np.mean(u_amp, axis=0), rtol=0.2)
