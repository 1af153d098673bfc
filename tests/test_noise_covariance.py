"""The simulator noise's covariance and the GLS noncentrality of the
oracle of scripts/power_curves.py --noise (rotcal.simulate.noise_covariance),
against independent truths: the hand formula under white noise, the dense
Cholesky GLS on a short series with gaps, and the simulator's own draws."""

import numpy as np
import pytest
from scipy.linalg import cho_factor, cho_solve

from rotcal.simulate.noise import NoiseSpec, draw_channels
from rotcal.simulate.noise_covariance import (
    SampleCovariance,
    autocovariance,
    dense_covariance,
    noncentrality,
    noncentrality_from,
    whittle_noncentrality,
)

FS = 1 / 0.06
MIX = NoiseSpec(white_sd=6.0, ar=(0.5,), ar_sd=4.0, lowpass_order=2, lowpass_cutoff=0.4,
                gauss_markov=((300.0, 2.0),), flicker_b=1.0, random_walk_k=0.02)


def toy(index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A baseline (constant, a slow sine pair, a step) and a signal partly in it."""
    basis = np.column_stack([np.ones(index.size), np.sin(2 * np.pi * index / 400), np.cos(2 * np.pi * index / 400),
                             (index > index.mean()).astype(float)])
    return 5 * np.sin(2 * np.pi * index / 37 + 0.3) + 0.01 * index + 3 * basis[:, 1], basis


def test_white_noise_is_the_hand_formula():
    # white noise of sd 3, no rounding: lambda = |(I - P_J) d|^2 / 9
    index = np.arange(500)
    delta, basis = toy(index)
    resid = delta - basis @ np.linalg.lstsq(basis, delta, rcond=None)[0]
    expected = resid @ resid / 9.0
    spec = NoiseSpec(white_sd=3.0)
    assert noncentrality(SampleCovariance(spec, FS, index, step=0.0), delta, basis) == pytest.approx(expected, rel=1e-9)
    assert whittle_noncentrality(spec, FS, delta, basis, step=0.0) == pytest.approx(expected, rel=1e-9)
    # the integer output's rounding: white of variance 1/12 more
    rounded = resid @ resid / (9.0 + 1 / 12)
    assert noncentrality(SampleCovariance(spec, FS, index), delta, basis) == pytest.approx(rounded, rel=1e-9)


@pytest.mark.parametrize("spec", [NoiseSpec(white_sd=2.0, ar=(0.9,), ar_sd=5.0), MIX], ids=["ar1", "mix"])
def test_exact_solve_is_the_dense_cholesky_gls_with_gaps(spec):
    rng = np.random.default_rng(3)
    index = rng.permutation(np.sort(rng.choice(900, 700, replace=False)))   # gaps, in no order
    delta, basis = toy(index)
    sigma = dense_covariance(spec, int(index.max()) + 1, FS)[np.ix_(index, index)]
    factor = cho_factor(sigma)
    dense = noncentrality_from(lambda b: cho_solve(factor, b), delta, basis)
    cov = SampleCovariance(spec, FS, index)
    assert noncentrality(cov, delta, basis) == pytest.approx(dense, rel=1e-7)
    # the product itself, against the dense matrix
    x = rng.standard_normal((index.size, 2))
    assert np.allclose(cov.matvec(x), sigma @ x, rtol=1e-10, atol=1e-9 * np.abs(sigma @ x).max())


def test_autocovariance_is_the_simulators():
    # the stationary part (no walk) against the simulator's draws: lags 0 to 5 within a few standard errors
    spec = NoiseSpec(white_sd=6.0, ar=(0.5,), ar_sd=4.0, lowpass_order=2, lowpass_cutoff=0.2,
                     gauss_markov=((0.5, 3.0),))
    n, channels = 400, 3000
    x = draw_channels(spec, n, FS, np.random.default_rng(7), channels)
    r = autocovariance(spec, n, FS, step=0.0)
    for lag in range(6):
        empirical = np.mean(x[: n - lag] * x[lag:])
        assert empirical == pytest.approx(r[lag], rel=0.03), lag
