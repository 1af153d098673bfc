"""The covariance of the noise's window means under the IEEE Std 952 terms
(rotcal.noise.means) against the sums over the windows' samples of each
term's autocovariance, and the flicker's against the simulator's draws."""

import numpy as np

from rotcal.noise.means import NoiseProcess, flicker_terms, window_mean_covariance
from rotcal.simulate.noise import NoiseSpec, draw_channels
from rotcal.simulate.noise import flicker_terms as simulated_flicker_terms

DT = 0.5


def sample_sums(kernel, windows: list[tuple[int, int]]) -> np.ndarray:
    """cov(mean_a, mean_b) = sum_i sum_j k(t_i, t_j) / (n_a n_b) over the windows' sample indices (a, b)."""
    out = np.empty((len(windows), len(windows)))
    for p, (a0, a1) in enumerate(windows):
        for q, (b0, b1) in enumerate(windows):
            i, j = np.arange(a0, a1)[:, None] * DT, np.arange(b0, b1)[None, :] * DT
            out[p, q] = kernel(i, j).mean()
    return out


WINDOWS = [(0, 400), (410, 500), (900, 1700), (1750, 1760)]


def as_times(windows):
    """Each window's first and last sample time, as the fit stage gives them."""
    return np.array([a * DT for a, _ in windows]), np.array([(b - 1) * DT for _, b in windows])


def test_gauss_markov_and_random_walk_means_equal_the_sample_sums():
    """A Gauss-Markov term (q 3, T 40 s) and a random walk (K 0.2) over four
    windows of 10 to 800 samples: the closed forms (continuous windows from
    the first to the last sample, plus half a sample either side) equal
    the discrete sums to 2 % (the discretisation of a window of 10
    samples), 0.5 % for the long ones."""
    start, stop = as_times(WINDOWS)
    half = DT / 2  # a sample stands for the interval about it
    gm = window_mean_covariance(NoiseProcess(gauss_markov=((40.0, 3.0),)), start - half, stop + half, DT, (0.0, 880.0))
    exact = sample_sums(lambda s, t: 9.0 * np.exp(-np.abs(s - t) / 40.0), WINDOWS)
    assert np.allclose(gm, exact, rtol=0.02), (gm / exact)
    rw = window_mean_covariance(NoiseProcess(random_walk_k=0.2), start - half, stop + half, DT, (-half, 880.0))
    exact = sample_sums(lambda s, t: 0.04 * (np.minimum(s, t) + half), WINDOWS)
    assert np.allclose(rw, exact, rtol=0.02), (rw / exact)


def test_white_noise_means_are_independent():
    """White density N over windows of n samples: N^2 / (n dt) on the
    diagonal (sd^2 / n), 0 between windows."""
    start, stop = as_times(WINDOWS)
    cov = window_mean_covariance(NoiseProcess(white_density=2.0), start - DT / 2, stop + DT / 2, DT, (0.0, 880.0))
    n = np.array([b - a for a, b in WINDOWS])
    assert np.allclose(np.diag(cov), 4.0 / (n * DT))
    assert np.all(cov[~np.eye(4, dtype=bool)] == 0.0)


def test_flicker_is_the_simulators_and_its_means_cover_its_draws():
    """Flicker of B = 2 over a 900 s record at 0.5 s: the same Gauss-Markov
    terms as the simulator draws, and over 2,000 draws the variances of the
    four windows' means and the covariance of the first and third (1.5 and
    6 minutes apart) within 20 % of the closed form (0.99 to 1.00 and 0.91;
    2,000 draws: +- 6 % at 2 sd for a variance, +- 15 % for that covariance)."""
    assert flicker_terms(2.0, DT, 1759 * DT) == simulated_flicker_terms(2.0, 1760 * DT, 1 / DT)
    start, stop = as_times(WINDOWS)
    cov = window_mean_covariance(NoiseProcess(flicker_b=2.0), start - DT / 2, stop + DT / 2, DT, (0.0, 1759 * DT))
    rng = np.random.default_rng(3)
    draws = draw_channels(NoiseSpec(flicker_b=2.0), 1760, 1 / DT, rng, 2000)
    means = np.stack([draws[a:b].mean(axis=0) for a, b in WINDOWS])
    measured = means @ means.T / 2000
    assert np.allclose(np.diag(measured) / np.diag(cov), 1.0, atol=0.2), np.diag(measured) / np.diag(cov)
    assert abs(measured[0, 2] / cov[0, 2] - 1) < 0.2, measured[0, 2] / cov[0, 2]
