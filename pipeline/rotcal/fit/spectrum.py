"""Segment fits' uncertainties from the noise's measured spectrum.

A segment fit's covariance Sigma (x) (X^T X)^-1 holds for white noise. For
a long record, least squares on trigonometric regressors has the variance
it would have under white noise of the noise's spectral density at the
regressors' frequency (Grenander 1954, Ann. Math. Statist. 25, 252): the
factor on a coefficient's variance is the density's ratio F to the white
level, at zero frequency for the offset C and at the rotation's frequency
for A and B (one cycle per segment for a static step sequence).

F is read from the residuals' periodogram (Percival & Walden 1993, ch. 6):
P_j = |sum_i r_i exp(-2 pi i j k / n)|^2 / n at the Fourier bins j of a
band about the regressor's bin (an octave either side; the bins within one
of it, which the fit emptied, left out; at least ``MIN_BINS``; the lowest
``LOW_BINS`` for zero frequency), over the residuals' mean square, pooled
over the segments of one rate and kind. Whatever the noise's shape (white,
autoregressive, a steep low-pass, a wander with a time constant below the
segment's duration), so measured F is the ratio Grenander's theorem needs.
For white noise each P_j / sigma^2 is exponential, so the band's mean over
m bins is Gamma(m, 1/m): F is applied only where it lies outside that
law's central 1 - ``SIGNIFICANCE`` interval, so white noise leaves fits as
they were.

A wander slower than a segment is measured between segments (``fit.wander``).
Measured in docs/method.md ("Coloured noise").
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import numpy as np
from scipy.special import digamma, gammainccinv, gammaincinv

# the fits are ``fit.segments.SegmentFit`` records (not imported: that module imports this one)
SegmentFit = Any

# periodogram ordinates are pooled in bands of a quarter octave on one frequency axis (Hz) for all segments
BANDS_PER_OCTAVE = 4
MIN_ORDINATES = 16
# zero frequency: the lowest bins only (a wander's density rises steeply there), fewer ordinates
MIN_ORDINATES_AT_ZERO = 8
# the wider windows that decide whether the noise is coloured where the narrow one holds few ordinates: a
# filter's mild colouring (a second-order low-pass at 0.4 of the sample rate: F = 1.27 below its corner) lies
# within the white law's interval for 64 ordinates (up to 1.46) and outside it for 512 (1.15)
WIDE_ORDINATES = (64, 512)
NOTCH_BINS = 1.0
# two-sided, per (segment group, channel): white noise keeps its uncertainties in 999 groups of 1000
SIGNIFICANCE = 1e-3


@dataclass(frozen=True, eq=False)
class Periodogram:
    """One segment's residual periodogram over its mean square, summed in
    quarter-octave bands (``band_index``) of frequency: ``sums`` (bands,
    channels) and ``counts``; with the frequencies (Hz) its offset and sine
    terms stand at (``targets_hz``: 0 and the rotation's, or one cycle per
    segment for static steps) and its lowest resolved frequency 1 / T."""

    bands: np.ndarray
    sums: np.ndarray
    counts: np.ndarray
    targets_hz: tuple[float, float]
    resolution_hz: float


def band_index(f_hz: np.ndarray) -> np.ndarray:
    """The quarter-octave band of each frequency (band k holds [2^(k/4), 2^((k+1)/4)) Hz)."""
    return np.floor(BANDS_PER_OCTAVE * np.log2(f_hz)).astype(np.int64)


def periodogram(resid: np.ndarray, dt_s: float, sine_cycles: float) -> Periodogram:
    """The banded periodogram of residuals (samples x channels) at sample
    interval ``dt_s`` whose sine terms make ``sine_cycles`` cycles over the
    segment; the bins within ``NOTCH_BINS`` of them, which the fit emptied,
    and zero frequency are left out."""
    n = resid.shape[0]
    power = np.abs(np.fft.rfft(resid, axis=0)[1:]) ** 2
    ss = np.einsum("ij,ij->j", resid, resid)
    power /= np.where(ss > 0, ss, 1.0)  # P_j / (n sigma^2): 1 on average for white noise
    bins = np.arange(1, power.shape[0] + 1)
    keep = np.abs(bins - sine_cycles) >= NOTCH_BINS
    f_hz = bins[keep] / (n * dt_s)
    index = band_index(f_hz)
    bands, where = np.unique(index, return_inverse=True)
    sums = np.stack([np.bincount(where, power[keep, r], bands.size) for r in range(power.shape[1])], axis=1)
    resolution = 1.0 / (n * dt_s)
    return Periodogram(bands, sums, np.bincount(where, minlength=bands.size).astype(float), (0.0, sine_cycles * resolution),
                       resolution)


def band_centre_hz(band: np.ndarray) -> np.ndarray:
    """The geometric middle of each quarter-octave band (``band_index``)."""
    return 2.0 ** ((np.asarray(band, float) + 0.5) / BANDS_PER_OCTAVE)


def _window(pooled: dict[int, tuple[np.ndarray, float]], low: float, high: float, enough: float
            ) -> tuple[np.ndarray, float, np.ndarray]:
    """The mean ordinate per channel over [low, high] Hz widened an octave
    either side at a time until it holds ``enough`` ordinates, their count
    and the bands taken."""
    keys = np.array(sorted(pooled))
    m, chosen = 0.0, keys[:0]
    for _ in range(16):
        chosen = keys[(keys >= band_index(np.array([low]))[0]) & (keys <= band_index(np.array([high]))[0])]
        m = sum(pooled[k][1] for k in chosen)
        if m >= enough:
            break
        low, high = low / 2, high * 2
    if m == 0:
        return np.ones(len(next(iter(pooled.values()))[0])), 0.0, chosen
    return np.asarray(sum(pooled[k][0] for k in chosen), float) / m, m, chosen


def _local_slope(pooled: dict[int, tuple[np.ndarray, float]], bands: np.ndarray, f_hz: float,
                 mean: np.ndarray) -> np.ndarray:
    """Each channel's density ratio at ``f_hz`` from a power law fitted to
    the ``bands``' mean ordinates (log mean on log frequency, each band
    weighted by its count, the log of a mean of c exponentials less its
    expectation psi(c) - ln c), where they span more than one band: a
    window widened to gather its ordinates is lopsided where a short record
    resolves nothing below the target (a wander's density falling as 1/f^2
    over a rotation of 2.5 cycles was read 30 % low by the window's mean);
    ``mean`` (the window's) where they do not. The caller takes the larger
    of the two: the ordinates of a noise-free record (rounding alone) fit
    no power law."""
    if bands.size < 2:
        return mean
    counts = np.array([pooled[int(k)][1] for k in bands], float)
    means = np.array([pooled[int(k)][0] for k in bands], float) / counts[:, None]
    x = np.log(band_centre_hz(bands) / f_hz)
    y = np.log(np.maximum(means, 1e-300)) - (digamma(counts) - np.log(counts))[:, None]
    design = np.column_stack([np.ones(bands.size), x]) * np.sqrt(counts)[:, None]
    coef = np.linalg.lstsq(design, y * np.sqrt(counts)[:, None], rcond=None)[0]
    return np.exp(coef[0])


@lru_cache(maxsize=256)
def _white_interval(m: float) -> tuple[float, float]:
    """The central 1 - ``SIGNIFICANCE`` interval of Gamma(m, 1/m) (scipy's quantiles cost 0.1 ms each)."""
    # scipy.special, not scipy.stats (its import costs every batch worker 0.3 s): the same inverses
    return float(gammaincinv(m, SIGNIFICANCE / 2)) / m, float(gammainccinv(m, SIGNIFICANCE / 2)) / m


def _coloured(ratio: np.ndarray, m: float) -> np.ndarray:
    """Where a mean of m ordinates departs from white noise's Gamma(m, 1/m)."""
    lo, hi = _white_interval(float(m))
    return (ratio < lo) | (ratio > hi)


def density_ratio_at(pooled: dict[int, tuple[np.ndarray, float]], f_hz: float, low_hz: float) -> np.ndarray:
    """Each channel's F at ``f_hz`` from the pooled bands (band -> (sums,
    count)): the mean ordinate over [f/2, 2f] (exact for a density falling
    as 1/f^2, 0.92 of it for 1/f), widened an octave at a time until it
    holds ``MIN_ORDINATES``, and where coloured at least the power law
    fitted to those bands at f (``_local_slope``); zero frequency is read in [low/4, low], low
    the segment's 1 / T, from at least ``MIN_ORDINATES_AT_ZERO``. 1 where
    white noise explains it (Gamma(m, 1/m)) there and in the windows widened
    to each of ``WIDE_ORDINATES``, which test with more power; where only a
    wide window departs, the largest of the windows' means up to it."""
    low, high = (f_hz / 2, 2 * f_hz) if f_hz > 0 else (low_hz / 4, low_hz)
    narrow, m, bands = _window(pooled, low, high, MIN_ORDINATES if f_hz > 0 else MIN_ORDINATES_AT_ZERO)
    if m == 0:
        return narrow
    on = _coloured(narrow, m)
    # where the narrow window passes for white, wider ones test with more power: where one departs, the
    # largest of the windows' means up to it (the narrow one is then noisy)
    wide_ratio, on_wide, largest = np.ones_like(narrow), np.zeros(narrow.shape, bool), narrow
    for enough in WIDE_ORDINATES:
        if (on | on_wide).all():  # every channel decided: a wider window changes nothing
            break
        wide, m_wide, _ = _window(pooled, low, high, enough)
        largest = np.maximum(largest, wide)
        newly = _coloured(wide, m_wide) & ~on_wide
        wide_ratio, on_wide = np.where(newly, largest, wide_ratio), on_wide | newly
    if f_hz > 0 and (on | on_wide).any():  # coloured: the density at f itself where above the window's mean
        narrow = np.maximum(narrow, _local_slope(pooled, bands, f_hz, narrow))
    return np.where(on, narrow, np.where(on_wide, np.maximum(narrow, wide_ratio), 1.0))


def spectrum_widened(fits: list[SegmentFit]) -> list[SegmentFit]:
    """``fits`` with covariance and rate uncertainty scaled by each
    channel's F at zero frequency (C) and at the sine terms' (A, B), read
    from the periodograms of all fits pooled on one frequency axis (the
    long rotations resolve the low frequencies a short static sequence's
    terms stand at); fits without a periodogram stay as they are."""
    pooled: dict[int, tuple[np.ndarray, float]] = {}
    for fit in fits:
        if fit.status == "ok" and fit.spectrum is not None:
            for k, sums, count in zip(fit.spectrum.bands, fit.spectrum.sums, fit.spectrum.counts):
                old = pooled.get(int(k), (0.0, 0.0))
                pooled[int(k)] = (old[0] + sums, old[1] + count)
    if not pooled:
        return fits
    windows: dict[tuple[float, float], np.ndarray] = {}

    def at(f_hz: float, low_hz: float) -> np.ndarray:  # fits of one rate and length share their windows
        if (f_hz, low_hz) not in windows:
            windows[f_hz, low_hz] = density_ratio_at(pooled, f_hz, low_hz)
        return windows[f_hz, low_hz]

    out = []
    for fit in fits:
        if fit.status != "ok" or fit.spectrum is None:
            out.append(fit)
            continue
        spec = fit.spectrum
        ratio = np.stack([at(f, spec.resolution_hz) for f in spec.targets_hz])
        scale = np.sqrt(np.column_stack([ratio[0], ratio[1], ratio[1]]).ravel())
        out.append(replace(fit, cov=fit.cov * np.outer(scale, scale), u_rate_fit_hz=fit.u_rate_fit_hz * float(np.sqrt(ratio[1].max())),
                           noise_ratio=ratio))
    return out
