"""The covariance of the simulator's noise (``simulate.noise.NoiseSpec``)
over a channel's samples, and the generalized least-squares (GLS)
noncentrality of a signal against a linear baseline under it: the
likelihood-ratio test that knows the true noise model
(``scripts/power_curves.py --noise``).

The drawn noise on the sensor's grid of consecutive samples 0..n-1
(``draw_channels``) is a stationary part plus a random walk:

- the Butterworth low-pass of white plus autoregressive noise, power
  spectral density |H(w)|^2 (white_sd^2 + sigma_e^2 / |1 - sum a_i e^-iwi|^2),
  its autocovariance by inverse FFT on a grid four times the series
  (the response decays geometrically: no aliasing at double precision);
- each Gauss-Markov term and each of flicker's (``flicker_terms`` for the
  grid's duration), autocovariance sd^2 a^|k|, a = exp(-dt / T), exactly;
- the output's rounding, white of variance step^2 / 12;
- the random walk from the first sample, covariance q^2 (min(i, j) + 1),
  q = K / sqrt(fs): C C' q^2 with C the cumulative sum, not stationary.

``SampleCovariance`` multiplies by the exact covariance of any subset of
the grid (the observed samples; the logger's pauses are gaps in it): the
Toeplitz part by circulant embedding and FFT, the walk by two cumulative
sums. Its solves are preconditioned conjugate gradients with the circulant
(Whittle) inverse of the whole grid's spectral density as preconditioner,
so they are exact to the tolerance, gaps and walk included.
``whittle_noncentrality`` is the approximation itself (FFT whitening of a
gapless series), kept to measure how far the approximation is from the
exact solve (tests/test_noise_covariance.py).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.signal import butter, sosfreqz

from rotcal.simulate.noise import NoiseSpec, ar_innovation_sd, flicker_terms


def _fft_size(n: int) -> int:
    return 1 << max(int(math.ceil(math.log2(max(n, 2)))), 4)


def _stationary_density(spec: NoiseSpec, m: int) -> np.ndarray:
    """The low-pass of white plus autoregression: its spectral density
    (variance per unit of 1/m) at w = 2 pi j / m, j = 0..m-1."""
    w = 2 * np.pi * np.arange(m) / m
    density = np.full(m, spec.white_sd**2)
    if spec.ar_sd and spec.ar:
        lags = np.arange(1, len(spec.ar) + 1)
        denominator = np.abs(1 - np.exp(-1j * np.outer(w, lags)) @ np.asarray(spec.ar, float)) ** 2
        density = density + ar_innovation_sd(spec.ar, spec.ar_sd) ** 2 / denominator
    if spec.lowpass_order:
        sos = butter(spec.lowpass_order, 2 * spec.lowpass_cutoff, output="sos")
        density = density * np.abs(sosfreqz(sos, worN=m, whole=True)[1]) ** 2
    return density


def _gauss_markov_terms(spec: NoiseSpec, n: int, fs_hz: float) -> tuple[tuple[float, float], ...]:
    return spec.gauss_markov + flicker_terms(spec.flicker_b, n / fs_hz, fs_hz)


def autocovariance(spec: NoiseSpec, n: int, fs_hz: float, step: float = 1.0) -> np.ndarray:
    """The stationary part's autocovariance at lags 0..n-1 (counts^2) on a
    grid of ``n`` samples at ``fs_hz``, the output rounded to ``step``."""
    m = _fft_size(4 * n)
    r = np.fft.ifft(_stationary_density(spec, m)).real[:n].copy()
    k = np.arange(n)
    for tau, sd in _gauss_markov_terms(spec, n, fs_hz):
        r += sd**2 * np.exp(-k / (fs_hz * tau))
    r[0] += step**2 / 12
    return r


def walk_variance(spec: NoiseSpec, fs_hz: float) -> float:
    """q^2: the random walk's variance per sample."""
    return spec.random_walk_k**2 / fs_hz


def dense_covariance(spec: NoiseSpec, n: int, fs_hz: float, step: float = 1.0) -> np.ndarray:
    """The whole (n, n) covariance of the grid (for checks on short series)."""
    r = autocovariance(spec, n, fs_hz, step)
    i = np.arange(n)
    return r[np.abs(i[:, None] - i[None, :])] + walk_variance(spec, fs_hz) * (np.minimum(i[:, None], i[None, :]) + 1)


def spectral_density(spec: NoiseSpec, n: int, fs_hz: float, m: int, step: float = 1.0) -> np.ndarray:
    """The grid's spectral density at w = 2 pi j / m (the circulant's
    eigenvalues): the stationary part's, the Gauss-Markov terms' Lorentzians
    (1 - a^2) sd^2 / |1 - a e^-iw|^2, rounding, and the walk's q^2 / (4 sin^2(w / 2)),
    at w = 0 the walk's value at the lowest frequency of a grid of ``n`` (its
    variance is bounded by the record's length)."""
    w = 2 * np.pi * np.arange(m) / m
    density = _stationary_density(spec, m) + step**2 / 12
    for tau, sd in _gauss_markov_terms(spec, n, fs_hz):
        a = math.exp(-1 / (fs_hz * tau))
        density = density + sd**2 * (1 - a * a) / np.abs(1 - a * np.exp(-1j * w)) ** 2
    q2 = walk_variance(spec, fs_hz)
    if q2:
        s2 = 4 * np.sin(w / 2) ** 2
        s2[0] = 4 * math.sin(math.pi / n) ** 2
        density = density + q2 / s2
    return density


class SampleCovariance:
    """The noise covariance of the samples at grid positions ``index``
    (0-based, on the sensor's grid of ``n`` consecutive samples; distinct,
    in any order), with exact products and preconditioned conjugate-gradient solves."""

    def __init__(self, spec: NoiseSpec, fs_hz: float, index: np.ndarray, n: int | None = None, step: float = 1.0):
        self.index = np.asarray(index, np.int64)
        if np.unique(self.index).size != self.index.size:
            raise ValueError("SampleCovariance: the samples' grid positions must be distinct")
        self.n = int(self.index.max()) + 1 if n is None else n
        self.size = _fft_size(2 * self.n)
        r = autocovariance(spec, self.n, fs_hz, step)
        c = np.zeros(self.size)
        c[:self.n] = r
        c[self.size - self.n + 1:] = r[1:][::-1]
        self._toeplitz = np.fft.rfft(c)
        self._q2 = walk_variance(spec, fs_hz)
        self._inverse = 1 / spectral_density(spec, self.n, fs_hz, self.size, step)[: self.size // 2 + 1]

    def _embedded(self, x: np.ndarray, length: int) -> np.ndarray:
        full = np.zeros((length, x.shape[1]))
        full[self.index] = x
        return full

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """Sigma x for x (len(index), p)."""
        full = self._embedded(x, self.size)
        y = np.fft.irfft(self._toeplitz[:, None] * np.fft.rfft(full, axis=0), self.size, axis=0)[:self.n]
        if self._q2:
            walk = full[:self.n]
            y += self._q2 * np.cumsum(np.cumsum(walk[::-1], axis=0)[::-1], axis=0)
        return y[self.index]

    def precondition(self, x: np.ndarray) -> np.ndarray:
        """The circulant (Whittle) approximation of Sigma^-1 x."""
        full = self._embedded(x, self.size)
        return np.fft.irfft(self._inverse[:, None] * np.fft.rfft(full, axis=0), self.size, axis=0)[self.index]

    def solve(self, b: np.ndarray, rtol: float = 1e-10, max_iter: int = 2000) -> tuple[np.ndarray, int]:
        """(Sigma^-1 b, iterations) by conjugate gradients on every column of
        ``b`` (len(index), p) at once, each to a residual ``rtol`` of its own."""
        b = np.asarray(b, float).reshape(len(self.index), -1)
        x = np.zeros_like(b)
        res = b.copy()
        z = self.precondition(res)
        p = z.copy()
        rz = np.sum(res * z, axis=0)
        target = rtol * np.linalg.norm(b, axis=0)
        for it in range(1, max_iter + 1):
            q = self.matvec(p)
            alpha = rz / np.where(np.sum(p * q, axis=0) == 0, 1.0, np.sum(p * q, axis=0))
            x += alpha * p
            res -= alpha * q
            if np.all(np.linalg.norm(res, axis=0) <= target):
                return x, it
            z = self.precondition(res)
            rz_new = np.sum(res * z, axis=0)
            p = z + (rz_new / np.where(rz == 0, 1.0, rz)) * p
            rz = rz_new
        raise RuntimeError(f"conjugate gradients: no convergence in {max_iter} iterations")


def noncentrality_from(solve, delta: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """lambda = d' S^-1 d - d' S^-1 J (J' S^-1 J)^-1 J' S^-1 d: the GLS
    likelihood ratio's noncentrality of each signal, a column of ``delta``
    (n, m) or (n,), against the baseline columns ``basis`` (n, p),
    ``solve(b)`` giving S^-1 b (one call, every column). Each signal is
    first cleared of its least-squares part in the basis (which leaves
    lambda as it is and keeps the difference well conditioned)."""
    d = np.asarray(delta, float).reshape(len(delta), -1)
    basis = np.asarray(basis, float).reshape(len(d), -1)
    d = d - basis @ np.linalg.lstsq(basis, d, rcond=None)[0]
    s = solve(np.column_stack([d, basis]))
    sd, sj = s[:, :d.shape[1]], s[:, d.shape[1]:]
    cross = basis.T @ sd
    out = np.sum(d * sd, axis=0) - np.sum(cross * np.linalg.solve(basis.T @ sj, cross), axis=0)
    return out if np.ndim(delta) == 2 else out[0]


def noncentrality(cov: SampleCovariance, delta: np.ndarray, basis: np.ndarray, rtol: float = 1e-10) -> np.ndarray:
    """The GLS noncentrality (``noncentrality_from``) under ``cov``, exactly (conjugate gradients)."""
    return noncentrality_from(lambda b: cov.solve(b, rtol)[0], delta, basis)


def whittle_noncentrality(spec: NoiseSpec, fs_hz: float, delta: np.ndarray, basis: np.ndarray,
                          step: float = 1.0) -> np.ndarray:
    """The same noncentrality with Sigma^-1 replaced by its circulant (Whittle)
    approximation on a gapless series of len(delta) samples: the FFT
    whitening W = F* diag(density^-1/2) F, lambda = |(I - P_WJ) W delta|^2."""
    n = len(delta)
    inverse = 1 / spectral_density(spec, n, fs_hz, n, step)

    def solve(b: np.ndarray) -> np.ndarray:
        return np.fft.ifft(inverse[:, None] * np.fft.fft(b, axis=0), axis=0).real

    return noncentrality_from(solve, delta, basis)
