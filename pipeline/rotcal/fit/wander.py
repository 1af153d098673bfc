"""The offset's wander between segments: the low-frequency floor of a
segment's offset uncertainty.

A wander slower than a segment (a bias instability, a random walk, a
Gauss-Markov term of long time constant) moves each segment's offset as a
whole, and a segment's residuals cannot see it. Under the model every
segment's C of a channel measures one offset O_r (Geist 2017 Eq. 5: the
gravity projection on a horizontal table axis is zero), so their scatter
beyond the fits' uncertainties measures the wander, once the deterministic
effects that move whole segments' offsets are allowed for (``offset_pattern``:
a linear drift in time, a shift per table axis and one growing with the
rate squared per axis, i.e. offset_drift, axis_tilt, centripetal; the
diagnosis tests those). Where the generalised Cochran's Q, the weighted
residual sum of squares of the offsets beyond that pattern, rejects it (at
``SIGNIFICANCE`` on n - rank degrees of freedom, per channel or pooled over
the channels: white noise, with or without those effects, leaves the fits
as they were), the offsets are taken as

    C_i = O_r + w(t_i) + e_i,   cov(w(t_i), w(t_j)) = s^2 exp(-|t_i - t_j| / tau),

a first-order Gauss-Markov wander at the segments' mid-times beside each
fit's own noise e_i (sized about one offset: on a plan that takes the axes
in turn a slow wander looks like a drift and per-axis shifts, which would
take most of it; the diagnosis then weighs those effects against the
wander), with s^2 per channel and tau shared by the channels,
by restricted maximum likelihood (Patterson & Thompson 1971, Biometrika 58,
545) on a grid. The stages after the fits take segments as independent, so
each segment of a group combined together (one rate and kind) carries the
variance that makes its group's mean right: s^2 times the mean of the
correlations over the group's pairs, itself included. Where the time
constant is longer than the record, the record cannot tell the wander's
size from the offset: s^2 is then taken at its upper 95 % profile-
likelihood bound (conservative), and the fits say so. With fewer than
``MIN_FLOOR_SEGMENTS`` segments nothing is identified, and the fits say so.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
from scipy.special import chdtri  # chi-square isf; scipy.stats costs every batch worker 0.3 s to import

# the fits are ``fit.segments.SegmentFit`` records (not imported: that module imports this one)
SegmentFit = Any

SIGNIFICANCE = 1e-3
MIN_FLOOR_SEGMENTS = 4
TAU_GRID = 25
VARIANCE_GRID = 41
UNIDENTIFIED = ("offset floor not identified (fewer than {k} segments of this channel): the offset's uncertainty "
                "holds the noise seen within segments only and may understate a slow wander")
SLOWER_THAN_RECORD = ("the offset wanders more slowly than the record lasts: its size is not identified, and the "
                      "floor is its upper 95 % likelihood bound (a longer record would measure it)")


def restricted_loglik(c: np.ndarray, v: np.ndarray, corr: np.ndarray, s2: np.ndarray, x: np.ndarray) -> np.ndarray:
    """REML log-likelihood (up to a constant) of offsets ``c`` with fit
    variances ``v`` under fixed effects ``x`` (segments, full column rank)
    and wander variances ``s2`` (each)."""
    out = np.empty(s2.size)
    for k, s in enumerate(s2):
        chol = np.linalg.cholesky(np.diag(v) + s * corr)
        a, b = np.linalg.solve(chol, x), np.linalg.solve(chol, c)
        q, r = np.linalg.qr(a)
        rss = b @ b - np.sum((q.T @ b) ** 2)
        out[k] = -np.sum(np.log(np.diag(chol))) - np.sum(np.log(np.abs(np.diag(r)))) - 0.5 * rss
    return out


def offset_pattern(t_s: np.ndarray, rate_hz: np.ndarray, axis: list[object]) -> np.ndarray:
    """The deterministic offset pattern's design (segments, columns): a
    common offset, a drift linear in time, and per table axis
    a shift and one proportional to the rate squared (a pose's rate is 0)."""
    t = t_s - t_s.mean()
    cols = [np.ones_like(t), t / max(float(np.abs(t).max()), 1e-9)]
    w2 = np.nan_to_num(np.asarray(rate_hz, float)) ** 2
    for a in sorted({str(a) for a in axis}):
        on = np.array([str(b) == a for b in axis], float)
        cols += [on, on * w2 / max(float(w2.max()), 1e-9)]
    return np.column_stack(cols)


def column_basis(x: np.ndarray) -> np.ndarray:
    """An orthonormal basis of ``x``'s column space (the axis shifts sum to
    the common offset; a rate may be single)."""
    u, sv, _ = np.linalg.svd(x, full_matrices=False)
    return u[:, sv > sv[0] * 1e-9]


def wander_fit(c: np.ndarray, v: np.ndarray, t_s: np.ndarray, tau_range: tuple[float, float], x: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray, float]:
    """(s^2 per channel, its upper 95 % profile-likelihood bound, tau) by
    REML over a grid: ``c``, ``v`` (segments, channels) offsets and their
    fit variances, ``t_s`` mid-times, ``x`` the offsets' fixed effects."""
    lag = np.abs(t_s[:, None] - t_s[None, :])
    taus = np.geomspace(*tau_range, TAU_GRID)
    spread = np.maximum(np.var(c, axis=0, ddof=1), np.mean(v, axis=0))
    grids = [np.r_[0.0, np.geomspace(1e-4, 100.0, VARIANCE_GRID - 1) * sd2] for sd2 in spread]
    best: tuple[float, float, list[np.ndarray]] = (-np.inf, taus[0], [])
    for tau in taus:
        corr = np.exp(-lag / tau)
        ll = [restricted_loglik(c[:, r], v[:, r], corr, grids[r], x) for r in range(c.shape[1])]
        total = sum(float(x.max()) for x in ll)
        if total > best[0]:
            best = (total, tau, ll)
    ll = best[2]
    s2 = np.array([grids[r][int(np.argmax(x))] for r, x in enumerate(ll)])
    # chi^2(1) 95 %: 3.84 / 2 below the profile's top
    upper = np.array([grids[r][np.flatnonzero(x >= x.max() - 1.92).max()] for r, x in enumerate(ll)])
    return s2, upper, float(best[1])


def offset_floor(fits: list[SegmentFit], t_mid_s: np.ndarray, duration_s: np.ndarray, groups: list[tuple[str, float]],
                 axis: list[object]) -> list[SegmentFit]:
    """``fits`` with each channel's offset wander added to their C
    variances (module docstring): ``t_mid_s``, ``duration_s`` each fit's
    mid-time and length, ``groups`` the key (kind, rate in Hz) of the fits
    combined together, ``axis`` each fit's table axis."""
    ok = [k for k, f in enumerate(fits) if f.status == "ok"]
    if not ok:
        return fits
    if len(ok) < MIN_FLOOR_SEGMENTS:
        note = UNIDENTIFIED.format(k=MIN_FLOOR_SEGMENTS)
        return [replace(f, noise_note=note) if f.status == "ok" else f for f in fits]
    c = np.array([fits[k].coef[:, 0] for k in ok])
    v = np.array([np.diag(fits[k].cov)[0::3] for k in ok])
    pattern = offset_pattern(t_mid_s[ok], np.array([groups[k][1] if groups[k][0] == "rotation" else 0.0 for k in ok], float),
                             [axis[k] for k in ok])
    x = column_basis(pattern)
    dof = len(ok) - x.shape[1]
    if dof < 1:
        return fits  # the pattern takes every segment: nothing left to measure a wander by
    sw = 1.0 / np.sqrt(np.maximum(v, 1e-300))
    q = np.empty(c.shape[1])
    for r in range(c.shape[1]):
        a, b = x * sw[:, r, None], c[:, r] * sw[:, r]
        q[r] = float(np.sum((b - a @ np.linalg.lstsq(a, b, rcond=None)[0]) ** 2))
    # the channels' scatter pooled as well: one wander test of the sensor, then its size per channel
    wanders = (q > chdtri(dof, SIGNIFICANCE)) | (q.sum() > chdtri(q.size * dof, SIGNIFICANCE))
    if not wanders.any():
        return fits
    t = t_mid_s[ok]
    span = float(t.max() - t.min())
    tau_top = 10.0 * max(span, 1e-9)
    # sized about a common offset: on a plan that takes the axes in turn a slow wander is a drift and a shift
    # per axis, so the pattern would take most of it (the diagnosis weighs the effects against the wander)
    s2, upper, tau = wander_fit(c, v, t, (max(float(np.min(duration_s[ok])) / 2, 1e-9), tau_top), pattern[:, :1])
    slower = tau >= span  # the record shows no wander's decorrelation: its size is a lower bound, the bound taken
    s2 = np.where(wanders, upper if slower else s2, 0.0)
    corr = np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
    key = [groups[k] for k in ok]
    flag = SLOWER_THAN_RECORD if slower else None
    out = list(fits)
    for i, k in enumerate(ok):
        members = [j for j in range(len(ok)) if key[j] == key[i]]
        floor = s2 * corr[np.ix_(members, members)].mean()
        cov = fits[k].cov.copy()
        cov[np.arange(0, 9, 3), np.arange(0, 9, 3)] += floor
        out[k] = replace(fits[k], cov=cov, offset_floor=np.sqrt(floor), noise_note=flag)
    return out
