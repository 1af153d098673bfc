"""The offsets' covariance between segments: the low-frequency floor of a
segment's offset uncertainty.

A wander slower than a segment (a bias instability, a random walk, a
Gauss-Markov term of long time constant) moves each segment's offset as a
whole, and a segment's residuals cannot see it. Two sources give the
offsets' covariance V (segments x segments, per channel):

1. The recording's noise model (``rotcal.noise``: the IEEE Std 952 terms
   identified from the residuals' Allan variance), where given: the
   covariance of each segment's mean of the noise under its white,
   flicker and Gauss-Markov terms (``noise.means``; the terms the data
   show at 2 u), flicker down to the record's length. That is the part
   common to segments far apart, which their scatter cannot show: a
   flicker slower than a segment moves every offset alike. Each diagonal
   element is at least the fit's own variance (the residuals' spectrum at
   zero frequency, ``fit.spectrum``).
2. The offsets' scatter beyond it. Under the model every segment's C of a
   channel measures one offset O_r (Geist 2017 Eq. 5), so their scatter
   beyond V measures what the model left out (a random walk, a wander
   slower than the Allan variance reaches), once the deterministic effects
   that move whole segments' offsets are allowed for (``offset_pattern``:
   a linear drift in time, a shift per table axis and one growing with the
   rate squared per axis, i.e. offset_drift, axis_tilt, centripetal; the
   diagnosis tests those). Where the generalised Cochran's Q, the offsets'
   residual sum of squares beyond that pattern weighted by V^-1 (generalised
   least squares), rejects it (at ``SIGNIFICANCE`` on n - rank degrees of
   freedom, per channel or pooled over the channels), the offsets are taken as

       C_i = O_r + w(t_i) + e_i,   cov(w(t_i), w(t_j)) = s^2 exp(-|t_i - t_j| / tau),

   a first-order Gauss-Markov wander at the segments' mid-times beside e
   of covariance V (sized about one offset: on a plan that takes the axes
   in turn a slow wander looks like a drift and per-axis shifts, which
   would take most of it; the diagnosis then weighs those effects against
   the wander), s^2 per channel and tau shared by the channels, by their
   restricted likelihood (Patterson & Thompson 1971, Biometrika 58, 545)
   on a grid: tau the likeliest with s^2 integrated over its grid (prior
   log-uniform), s^2 its posterior mean at that tau (the likelihood's mode
   of a variance from a dozen offsets is low: its normalised errors have
   t-like tails). Where tau is longer than the record, the record cannot
   tell the wander's size from the offset: s^2 is then taken at its upper
   95 % profile-likelihood bound (conservative), and the fits say so.

The stages after the fits take segments as independent and combine the
segments of one rate and kind by their inverse-variance weighted mean. Each
segment of such a group carries the offset variance d_i + F: d_i its own
variance under V (plus the wander), F the group's one addition that makes
the weighted mean's variance 1 / sum 1 / (d_i + F) equal its variance under
the full covariance, w^T V w with those weights (solved by fixed point):
the equivalent of generalised least squares for a mean whose segments share
a wander. With fewer than ``MIN_FLOOR_SEGMENTS`` segments the scatter is
not tested, and the fits say so.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.special import chdtri, logsumexp, softmax  # scipy.stats costs every batch worker 0.3 s to import

from rotcal.noise.means import NoiseProcess, window_mean_covariance

# the fits are ``fit.segments.SegmentFit`` records (not imported: that module imports this one)
SegmentFit = Any

SIGNIFICANCE = 1e-3
MIN_FLOOR_SEGMENTS = 4
TAU_GRID = 25
VARIANCE_GRID = 41
UNIDENTIFIED = ("offsets' scatter between segments not tested (fewer than {k} segments of this channel): the offset's "
                "uncertainty holds the noise model's and may understate a wander slower than the segments")
NOT_MODELLED = ("the noise is coloured but its model could not be identified (too few averaging times in the "
                "residuals): the offsets' covariance is their scatter's alone, its wander at the upper 95 % likelihood "
                "bound, and a wander every segment shares is not in u")
SLOWER_THAN_RECORD = ("the offset wanders more slowly than the record lasts: its size is not identified, and the "
                      "floor is its upper 95 % likelihood bound (a longer record would measure it)")


@dataclass(frozen=True)
class RecordNoise:
    """The recording's noise model as the offsets' covariance needs it:
    each channel's process (``noise.means``), the sample interval and the
    record's first and last sample times (s)."""

    processes: tuple[NoiseProcess, ...]
    dt_s: float
    record_s: tuple[float, float]


@dataclass(frozen=True, eq=False)
class Wander:
    """The wander the offsets' scatter shows beyond the noise model (part 2
    of the module docstring): variance ``s2`` per channel, correlation
    exp(-|t_i - t_j| / tau) between times t (s, the record's clock), or
    (tau infinite) a random walk from ``start_s`` whose variance is s2 at
    ``walk_s`` after it; ``slower``: tau is longer than the record (s2 its
    upper bound)."""

    s2: np.ndarray
    tau_s: float
    start_s: float
    walk_s: float
    slower: bool

    def correlation(self, t_s: np.ndarray) -> np.ndarray:
        if np.isinf(self.tau_s):
            since = np.maximum(t_s - self.start_s, 0.0)
            return np.minimum.outer(since, since) / max(self.walk_s, 1e-9)
        return np.exp(-np.abs(t_s[:, None] - t_s[None, :]) / self.tau_s)


@dataclass(frozen=True, eq=False)
class OffsetCovariance:
    """The offsets' covariance between any windows of the record as the
    segments' was built: the recording's noise model (part 1) in its
    ``coloured`` channels, and the ``wander`` their scatter showed beyond
    it (part 2). What a static pose's mean between the segments shares
    with them (``combine.unreferenced``: an unlabelled recording's dwells)."""

    noise: RecordNoise | None
    coloured: np.ndarray
    wander: Wander | None

    def channels(self, start_s: np.ndarray, stop_s: np.ndarray, own: list[np.ndarray]) -> list[np.ndarray]:
        """Each channel's covariance (n, n) of the means over the windows
        [start_s, stop_s]: the noise model's (its diagonal at least the
        windows' ``own``), ``own`` as given where the channel is white, plus
        the wander at the windows' mid-times."""
        base = model_covariance(self.noise, own, start_s, stop_s, self.coloured)
        if self.wander is None:
            return base
        corr = self.wander.correlation((start_s + stop_s) / 2)
        return [b + s * corr for b, s in zip(base, self.wander.s2)]


def restricted_loglik(c: np.ndarray, base: np.ndarray, corr: np.ndarray, s2: np.ndarray, x: np.ndarray) -> np.ndarray:
    """REML log-likelihood (up to a constant) of offsets ``c`` of
    covariance ``base`` under fixed effects ``x`` (segments, full column
    rank) and wander variances ``s2`` (each)."""
    out = np.empty(s2.size)
    for k, s in enumerate(s2):
        chol = np.linalg.cholesky(base + s * corr)
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


def wander_fit(c: np.ndarray, base: list[np.ndarray], t_s: np.ndarray, tau_range: tuple[float, float], x: np.ndarray,
               since_start_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(s^2 per channel, its upper 95 % profile-likelihood bound, tau) by
    restricted likelihood over a grid (s^2 its posterior mean at the
    likeliest tau): ``c`` (segments, channels) offsets, ``base`` each
    channel's covariance of them without the wander, ``t_s`` mid-times,
    ``x`` the offsets' fixed effects; tau infinite for a random walk from
    the record's start (``since_start_s``: the mid-times after it, the
    variance s^2 at the last), which the grid holds beside the
    Gauss-Markov terms."""
    lag = np.abs(t_s[:, None] - t_s[None, :])
    taus = np.r_[np.geomspace(*tau_range, TAU_GRID), np.inf]
    walk = np.minimum.outer(since_start_s, since_start_s) / max(float(since_start_s.max()), 1e-9)
    spread = np.maximum(np.var(c, axis=0, ddof=1), [np.mean(np.diag(b)) for b in base])
    grids = [np.r_[0.0, np.geomspace(1e-4, 100.0, VARIANCE_GRID - 1) * sd2] for sd2 in spread]
    best: tuple[float, float, list[np.ndarray]] = (-np.inf, taus[0], [])
    for tau in taus:
        corr = walk if np.isinf(tau) else np.exp(-lag / tau)
        ll = [restricted_loglik(c[:, r], base[r], corr, grids[r], x) for r in range(c.shape[1])]
        # each tau by its likelihood with s^2 integrated over the grid (its prior: log-uniform, and 0)
        total = sum(float(logsumexp(channel)) for channel in ll)
        if total > best[0]:
            best = (total, tau, ll)
    ll = best[2]
    # s^2 at its posterior mean, not its mode: a variance from a dozen offsets is uncertain and its likelihood
    # leans to larger values (the default plan's random-walk O at 0.1 and 0.5 Hz: 89 % within 2 u with the
    # mode and the profile's tau, 92 and 93 % with the mean and the integrated; docs/measured.md)
    s2 = np.array([grids[r] @ softmax(channel) for r, channel in enumerate(ll)])
    # chi^2(1) 95 %: 3.84 / 2 below the profile's top
    upper = np.array([grids[r][np.flatnonzero(channel >= channel.max() - 1.92).max()] for r, channel in enumerate(ll)])
    return s2, upper, float(best[1])


def generalised_q(c: np.ndarray, base: np.ndarray, x: np.ndarray) -> float:
    """The offsets' residual sum of squares beyond ``x`` weighted by ``base``^-1."""
    chol = np.linalg.cholesky(base)
    a, b = np.linalg.solve(chol, x), np.linalg.solve(chol, c)
    return float(np.sum((b - a @ np.linalg.lstsq(a, b, rcond=None)[0]) ** 2))


def model_covariance(noise: RecordNoise | None, own: list[np.ndarray], start_s: np.ndarray, stop_s: np.ndarray,
                     coloured: np.ndarray) -> list[np.ndarray]:
    """Each channel's covariance of the means over the windows [start_s,
    stop_s] without a wander beyond the noise model: the model's (part 1 of
    the module docstring), its diagonal at least that of the windows' own
    covariance ``own`` (per channel, n x n); ``own`` as given without a
    model or where the channel is not ``coloured``."""
    out = []
    for r, base in enumerate(own):
        if noise is None or r >= len(noise.processes) or not coloured[r]:
            out.append(base)
            continue
        cov = window_mean_covariance(noise.processes[r], start_s, stop_s, noise.dt_s, noise.record_s)
        cov[np.diag_indices_from(cov)] = np.maximum(np.diag(cov), np.diag(base))
        out.append(cov)
    return out


def group_widening(cov: np.ndarray) -> float:
    """F of the module docstring for one group's covariance ``cov``: the
    addition to each diagonal element after which the inverse-variance
    weighted mean's variance as if independent equals its variance under
    ``cov`` (at least 0)."""
    d = np.diag(cov)
    f = 0.0
    for _ in range(8):  # the weights move little with F: a few fixed-point steps settle it
        w = 1.0 / (d + f)
        w /= w.sum()
        target = float(w @ cov @ w)
        new = max(target * len(d) - float(np.mean(d)), 0.0) if len(d) > 1 else 0.0
        # exact for equal d; otherwise refine with 1 / sum 1 / (d + F) = target
        for _ in range(20):
            g = 1.0 / np.sum(1.0 / (d + new)) - target
            slope = np.sum((d + new) ** -2.0) / np.sum(1.0 / (d + new)) ** 2
            step = g / slope
            new = max(new - step, 0.0)
            if abs(step) <= 1e-12 * (float(d.max()) + new):
                break
        if abs(new - f) <= 1e-9 * max(float(d.max()), 1e-300):
            return new
        f = new
    return f


def offset_floor(fits: list[SegmentFit], t_mid_s: np.ndarray, duration_s: np.ndarray, groups: list[tuple[str, float]],
                 axis: list[object], noise: RecordNoise | None = None, modelled: bool = False,
                 record_start_s: float | None = None) -> list[SegmentFit]:
    """``fits`` with each channel's offset covariance between segments
    folded into their C variances (module docstring): ``t_mid_s``,
    ``duration_s`` each fit's mid-time and length, ``groups`` the key
    (kind, rate in Hz) of the fits combined together, ``axis`` each fit's
    table axis, ``noise`` the recording's noise model (None: the scatter
    alone), ``modelled`` whether the caller tried to identify one (where it
    failed on coloured noise, the scatter's wander is taken at its upper
    bound and the fits say so), ``record_start_s`` where a random walk
    starts (``scatter_wander``)."""
    ok = [k for k, f in enumerate(fits) if f.status == "ok"]
    if not ok:
        return fits
    c = np.array([fits[k].coef[:, 0] for k in ok])
    v = np.array([np.diag(fits[k].cov)[0::3] for k in ok])
    t = t_mid_s[ok]
    half = duration_s[ok] / 2
    # the model where the fits' residuals show a density above white at zero frequency (``fit.spectrum``):
    # white noise leaves the offsets as they were
    coloured = np.array([any(fits[k].noise_ratio is not None and fits[k].noise_ratio[0, r] > 1.0 for k in ok)
                         for r in range(c.shape[1])])
    base = model_covariance(noise, [np.diag(v[:, r]) for r in range(v.shape[1])], t - half, t + half, coloured)
    total, flag, wander = base, None, None
    unmodelled = noise is None and bool(coloured.any()) and modelled
    if len(ok) < MIN_FLOOR_SEGMENTS:
        flag = UNIDENTIFIED.format(k=MIN_FLOOR_SEGMENTS)
    else:
        wander = scatter_wander(c, base, t, duration_s[ok], [groups[k] for k in ok], [axis[k] for k in ok], unmodelled,
                                record_start_s)
        if wander is not None:
            corr = wander.correlation(t)
            total = [b + s * corr for b, s in zip(base, wander.s2)]
            flag = SLOWER_THAN_RECORD if wander.slower else None
    flag = NOT_MODELLED if unmodelled and len(ok) >= MIN_FLOOR_SEGMENTS else flag
    if total is base and not (noise is not None and coloured.any()):  # white noise, no wander: the fits as they were
        return [replace(fits[k], noise_note=flag) if fits[k].status == "ok" and flag else fits[k] for k in range(len(fits))]
    shared = OffsetCovariance(noise, coloured, wander)
    key = [groups[k] for k in ok]
    added = np.zeros(v.shape)
    for g in dict.fromkeys(key):
        members = [i for i in range(len(ok)) if key[i] == g]
        for r in range(c.shape[1]):
            block = total[r][np.ix_(members, members)]
            added[members, r] = np.diag(block) + group_widening(block) - v[members, r]
    added = np.maximum(added, 0.0)
    out = list(fits)
    for i, k in enumerate(ok):
        if not added[i].any():
            out[k] = replace(fits[k], noise_note=flag, offsets=shared)
            continue
        cov = fits[k].cov.copy()
        cov[np.arange(0, 9, 3), np.arange(0, 9, 3)] += added[i]
        out[k] = replace(fits[k], cov=cov, offset_floor=np.sqrt(added[i]), noise_note=flag, offsets=shared)
    return out


def scatter_wander(c: np.ndarray, base: list[np.ndarray], t: np.ndarray, duration_s: np.ndarray,
                   key: list[tuple[str, float]], axis: list[object], conservative: bool = False,
                   record_start_s: float | None = None) -> Wander | None:
    """The wander the offsets' scatter shows beyond ``base`` (part 2 of the
    module docstring), or None where the scatter is explained; ``conservative``: s^2 at its upper bound whatever tau. A
    random walk starts at ``record_start_s`` (None: the first segment's
    start; a recording whose first segment comes late, after the dwells of
    an unlabelled one, has walked meanwhile)."""
    pattern = offset_pattern(t, np.array([g[1] if g[0] == "rotation" else 0.0 for g in key], float), axis)
    x = column_basis(pattern)
    dof = len(t) - x.shape[1]
    if dof < 1:
        return None  # the pattern takes every segment: nothing left to measure a wander by
    q = np.array([generalised_q(c[:, r], base[r], x) for r in range(c.shape[1])])
    # the channels' scatter pooled as well: one wander test of the sensor, then its size per channel
    wanders = (q > chdtri(dof, SIGNIFICANCE)) | (q.sum() > chdtri(q.size * dof, SIGNIFICANCE))
    if not wanders.any():
        return None
    span = float(t.max() - t.min())
    tau_top = 10.0 * max(span, 1e-9)
    first = float(np.min(t - duration_s / 2))
    since = t - (first if record_start_s is None else min(record_start_s, first))
    s2, upper, tau = wander_fit(c, base, t, (max(float(np.min(duration_s)) / 2, 1e-9), tau_top), pattern[:, :1], since)
    # the record shows no wander's decorrelation: its size is a lower bound, the bound taken (a random walk's
    # growth measures its size)
    slower = span <= tau < np.inf
    s2 = np.where(wanders, upper if slower or conservative else s2, 0.0)
    return Wander(s2, tau, float(t[0] - since[0]), float(since.max()), slower)
