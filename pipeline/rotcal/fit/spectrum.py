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

A wander slower than a segment (a bias instability, a random walk, a
Gauss-Markov term of long time constant) moves each segment's offset as a
whole, and a segment's residuals cannot see it. Under the model every
segment's C of a channel measures one offset O_r (Geist 2017 Eq. 5: the
gravity projection on a horizontal table axis is zero), so their scatter
beyond the fits' uncertainties measures the wander at the segments' scale:
the between-segment variance tau^2 of a random-effects model, estimated by
DerSimonian & Laird (1986, Control. Clin. Trials 7, 177), is added to every
segment's offset variance where Cochran's Q rejects equal offsets. With
fewer than ``MIN_FLOOR_SEGMENTS`` segments it cannot be identified: the
fits say so (``noise_note``). Measured in docs/method.md ("Coloured noise").
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np
from scipy.stats import chi2, gamma

if TYPE_CHECKING:
    from rotcal.fit.segments import SegmentFit

LOW_BINS = 6
MIN_BINS = 4
NOTCH_BINS = 1.0
# two-sided, per (rate, channel): white noise keeps its uncertainties in 999 groups of 1000
SIGNIFICANCE = 1e-3
MIN_FLOOR_SEGMENTS = 4
FLOOR_UNIDENTIFIED = ("offset floor not identified (fewer than {k} segments of this channel): the offset's "
                      "uncertainty holds the noise seen within segments only and may understate a slow wander")


def band(target_bin: float, n: int) -> np.ndarray:
    """The Fourier bins (1 .. n // 2) whose density stands for the regressor
    at bin ``target_bin`` (cycles per segment; 0 for the offset)."""
    bins = np.arange(1, n // 2 + 1)
    eligible = bins[np.abs(bins - target_bin) >= NOTCH_BINS]
    if target_bin < 1.0:
        return eligible[:LOW_BINS]
    chosen = eligible[(eligible >= target_bin / 2) & (eligible <= 2 * target_bin)]
    if chosen.size >= MIN_BINS:
        return chosen
    return np.sort(eligible[np.argsort(np.abs(np.log(eligible / target_bin)), kind="stable")[:MIN_BINS]])


def band_power(resid: np.ndarray, target_bins: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Per target, the sum over its band of each channel's periodogram over
    the residuals' mean square (targets x channels), and the band's bin count."""
    n = resid.shape[0]
    power = np.abs(np.fft.rfft(resid, axis=0)) ** 2
    ss = np.einsum("ij,ij->j", resid, resid)
    norm = np.where(ss > 0, ss, 1.0)
    chosen = [band(t, n) for t in target_bins]
    return np.stack([power[j].sum(axis=0) / norm for j in chosen]), np.array([j.size for j in chosen], float)


def pooled_ratio(sums: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """F from pooled band sums (targets, channels) over ``counts`` bins, 1
    where it is consistent with white noise (Gamma(m, 1/m))."""
    m = np.maximum(counts, 1.0)[:, None]
    ratio = sums / m
    low, high = gamma.ppf(SIGNIFICANCE / 2, m, scale=1 / m), gamma.isf(SIGNIFICANCE / 2, m, scale=1 / m)
    return np.where((ratio < low) | (ratio > high), ratio, 1.0)


def spectrum_widened(fits: list[SegmentFit], groups: list[object]) -> list[SegmentFit]:
    """``fits`` with covariance and rate uncertainty scaled by F at zero
    (C) and at the rotation's frequency (A, B), pooled over fits of one
    group (a rate and kind); fits without band sums stay as they are."""
    pooled: dict[object, list[np.ndarray]] = {}
    for fit, key in zip(fits, groups):
        if fit.status == "ok" and fit.spectrum is not None:
            sums, counts = fit.spectrum
            acc = pooled.setdefault(key, [np.zeros_like(sums), np.zeros_like(counts)])
            acc[0] += sums
            acc[1] += counts
    out = []
    for fit, key in zip(fits, groups):
        if key not in pooled or fit.status != "ok":
            out.append(fit)
            continue
        ratio = pooled_ratio(*pooled[key])  # (2 targets, channels)
        scale = np.sqrt(np.column_stack([ratio[0], ratio[1], ratio[1]]).ravel())
        out.append(replace(fit, cov=fit.cov * np.outer(scale, scale), u_rate_fit_hz=fit.u_rate_fit_hz * float(np.sqrt(ratio[1].max())),
                           noise_ratio=np.stack([ratio[0], ratio[1]])))
    return out


def offset_floor(fits: list[SegmentFit]) -> list[SegmentFit]:
    """``fits`` with each channel's between-segment offset variance tau^2
    (DerSimonian-Laird, applied where Cochran's Q rejects one offset at
    ``SIGNIFICANCE``) added to every segment's C variance; where too few
    segments identify it, the fits carry the note instead."""
    ok = [k for k, f in enumerate(fits) if f.status == "ok"]
    if not ok:
        return fits
    if len(ok) < MIN_FLOOR_SEGMENTS:
        note = FLOOR_UNIDENTIFIED.format(k=MIN_FLOOR_SEGMENTS)
        return [replace(f, noise_note=note) if f.status == "ok" else f for f in fits]
    c = np.array([fits[k].coef[:, 0] for k in ok])  # (segments, channels)
    var = np.array([np.diag(fits[k].cov)[0::3] for k in ok])
    w = 1.0 / np.maximum(var, 1e-300)
    mean = (w * c).sum(axis=0) / w.sum(axis=0)
    q = (w * (c - mean) ** 2).sum(axis=0)
    dof = len(ok) - 1
    spread = w.sum(axis=0) - (w**2).sum(axis=0) / w.sum(axis=0)
    tau2 = np.where(q > chi2.isf(SIGNIFICANCE, dof), np.maximum(q - dof, 0.0) / spread, 0.0)
    if not np.any(tau2 > 0):
        return fits
    out = list(fits)
    for k in ok:
        cov = fits[k].cov.copy()
        cov[np.arange(0, 9, 3), np.arange(0, 9, 3)] += tau2
        out[k] = replace(fits[k], cov=cov, offset_floor=np.sqrt(tau2))
    return out
