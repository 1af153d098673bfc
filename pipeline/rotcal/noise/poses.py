"""Static poses' means under the recording's noise: each pose mean's
variance and the covariance between pose means, per channel, from the
noise model identified from the poses' own residuals (each pose's samples
less its mean; ``noise.model``, IEEE Std 952 / 1293 terms) as
``noise.means.window_mean_covariance`` gives a window's mean, the same
terms the table segments' offsets take (``fit.wander`` part 1).

A wander slower than a pose (a Gauss-Markov term of long correlation
time, a random walk, flicker below the poses' averaging times) moves
every pose's mean, and poses minutes apart together; a pose's residuals
barely see it. Its size beyond the model is measured, as ``fit.wander``
part 2 measures the segments' offsets', from the poses' scatter about the
static model (``wandering_covariance``): a first-order Gauss-Markov wander
(or a random walk from the record's start) by restricted maximum likelihood
(Patterson & Thompson 1971) where the generalised Cochran's Q of the
residuals rejects the model's covariance at ``fit.wander.SIGNIFICANCE``;
the reductions then weigh the poses by generalised least squares with the
full covariance, so the offsets carry the wander every pose shares.

Where the channel's model cannot be identified (poses too short for five
averaging times), its poses keep their own covariance (the lag widening of
``fit.means``), the between-pose wander rests on the scatter alone at its
upper 95 % likelihood bound, and the note says so. White noise keeps the
poses' own variances (the model adds nothing a pose's scatter does not show).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rotcal.fit.wander import SIGNIFICANCE, generalised_q, restricted_loglik, wander_fit
from rotcal.noise.allan import pooled_avars
from rotcal.noise.means import process_of, short_record_process, window_mean_covariance
from rotcal.noise.model import identify_channel
from rotcal.noise.residuals import split_at_pauses

UNMODELLED = ("the poses are too short to identify the noise model of channel(s) {channels} (fewer than five averaging "
              "times): their means keep their own scatter's variance, and a wander between poses is taken at its upper "
              "95 % likelihood bound")
SLOWER_THAN_RECORD = ("the poses' means wander more slowly than the record lasts: the wander's size is not identified, "
                      "and its upper 95 % likelihood bound is taken")
TAU_GRID = 25
MISFIT = 3.0  # a noise model's reduced chi-square beyond it: the model misses its own Allan variance
VARIANCE_GRID = 41


@dataclass(frozen=True, eq=False)
class PoseCovariance:
    """The pose means' covariance between poses: per channel (3, n, n),
    the poses' mid-times and lengths (s, on the record's clock from its
    first sample), whether each channel's noise model was identified, and
    what the covariance could not identify (None: nothing)."""

    channels: np.ndarray
    t_mid_s: np.ndarray
    duration_s: np.ndarray
    modelled: np.ndarray
    note: str | None = None

    def projected(self, h: np.ndarray) -> np.ndarray:
        """The covariance (n, n) of the scalars sum_r h_kr m_kr of the pose
        means (``h`` (n, 3), e.g. d|a_k|/dm_k), the channels' noise taken as
        independent (a covariance between channels within a pose alone,
        beside one between poses per channel, need not be positive
        definite; the noise model is per channel)."""
        return np.einsum("kr,rkl,lr->kl", h, self.channels, h)


def pose_covariance(t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray, stops: np.ndarray,
                    own: np.ndarray) -> PoseCovariance:
    """The noise model's covariance between the means of the poses
    ``starts[k]:stops[k]`` of samples ``y`` (n, 3) stamped ``t_ns``;
    ``own`` (poses, 3, 3) their own covariances (``fit.means``), kept where
    the model is not identified or the noise is white."""
    dt = float(np.median(np.diff(t_ns))) / 1e9 if t_ns.size > 1 else 0.0
    t0 = float(t_ns[0]) if t_ns.size else 0.0
    first, last = (t_ns[starts] - t0) / 1e9, (t_ns[stops - 1] - t0) / 1e9
    a0, a1 = first - dt / 2, last + dt / 2  # a sample stands for its interval
    record = (-dt / 2, (float(t_ns[-1]) - t0) / 1e9 + dt / 2 if t_ns.size else 0.0)
    n = len(starts)
    channels = np.zeros((3, n, n))
    modelled = np.zeros(3, bool)
    pieces = [p for a, b in zip(starts, stops) if b - a >= 2
              for p in split_at_pauses(t_ns[a:b], y[a:b] - y[a:b].mean(axis=0), dt)] if dt > 0 else []
    allan = pooled_avars(pieces, 1 / dt) if pieces else []
    for r in range(3):
        channels[r][np.diag_indices(n)] = own[:, r, r]
        if not pieces:
            continue
        noise = identify_channel("", [p[:, r] for p in pieces], 1 / dt, "", allan[r])
        if noise.reason:
            continue
        modelled[r] = True
        # a pose's Allan variance reaches a few seconds: the terms shorter than its longest averaging time
        # are a filter's or an autoregression's; a slower one is shared between poses only where the data
        # show it (the scatter between poses measures the rest, ``channel_wander``), while each pose's
        # own variance holds the slower terms at their fitted values where they lift the longest octaves
        shown = window_mean_covariance(short_record_process(noise, float(noise.allan.tau_s[-1])), a0, a1, dt, record)
        if noise.chi2_reduced > MISFIT:  # a model that misses its own Allan variance: each pose's own scatter at least
            shown[np.diag_indices(n)] = np.maximum(np.diag(shown), own[:, r, r])
        channels[r] = shown
    missing = [c for c, ok in zip("uvw", modelled) if not ok]
    note = UNMODELLED.format(channels=", ".join(missing)) if missing else None
    return PoseCovariance(channels, (a0 + a1) / 2, a1 - a0, modelled, note)


def with_pose_variances(cov: np.ndarray, between: PoseCovariance) -> np.ndarray:
    """The poses' own covariances (n, 3, 3) with each channel's variance
    that of ``between`` (its diagonal), the channels' correlations kept."""
    sd_own = np.sqrt(np.einsum("kii->ki", cov))
    sd = np.sqrt(np.einsum("rkk->kr", between.channels))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(sd_own > 0, sd / sd_own, 1.0)
    return cov * scale[:, :, None] * scale[:, None, :]


def _taus(between: PoseCovariance) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The wander's correlation times (s; the last inf, a random walk) and
    the poses' lags and times since the record's start."""
    t = between.t_mid_s
    span = float(t.max() - t.min()) if t.size else 0.0
    low = max(float(np.min(between.duration_s)) / 2, 1e-9) if t.size else 1.0
    taus = np.r_[np.geomspace(low, max(10.0 * span, 2 * low), TAU_GRID), np.inf]
    return taus, np.abs(t[:, None] - t[None, :]), t - (t - between.duration_s / 2).min()


def _correlation(tau: float, lag: np.ndarray, since: np.ndarray) -> np.ndarray:
    return np.minimum.outer(since, since) / max(float(since.max()), 1e-9) if np.isinf(tau) else np.exp(-lag / tau)


def channel_wander(between: PoseCovariance, residual_basis: np.ndarray, means: np.ndarray) -> PoseCovariance:
    """``between`` with each channel's wander beyond the noise model,
    measured from the pose means ``means`` (n, 3) about a model linear in
    ``residual_basis`` (n, p; e.g. the known references and 1) per channel:
    ``fit.wander.wander_fit``, where the generalised Q rejects the model's
    covariance (per channel or pooled)."""
    n, p = residual_basis.shape
    if n - p < 1:
        return between
    base = [between.channels[r] for r in range(3)]
    q = np.array([generalised_q(means[:, r], base[r], residual_basis) for r in range(3)])
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    wanders = (q > chdtri(n - p, SIGNIFICANCE)) | (q.sum() > chdtri(3 * (n - p), SIGNIFICANCE)) | ~between.modelled
    if not wanders.any():
        return between
    taus, lag, since = _taus(between)
    # the residuals of least squares: REML sees only what the model leaves, and they size its variance grid
    resid = means - residual_basis @ np.linalg.lstsq(residual_basis, means, rcond=None)[0]
    s2, upper, tau = wander_fit(resid, base, between.t_mid_s, (taus[0], taus[-2]), residual_basis, since)
    slower = float(np.ptp(between.t_mid_s)) <= tau < np.inf
    conservative = slower | ~between.modelled
    s2 = np.where(wanders, np.where(conservative, upper, s2), 0.0)
    corr = _correlation(tau, lag, since)
    note = between.note or (SLOWER_THAN_RECORD if slower and wanders.any() else None)
    return replace(between, channels=between.channels + s2[:, None, None] * corr[None], note=note)


def scalar_wander(between: PoseCovariance, residuals: np.ndarray, h: np.ndarray, design: np.ndarray) -> PoseCovariance:
    """``between`` with a wander beyond the noise model measured from
    scalar residuals of the pose means (``residuals`` (n,) = sum_r h_kr
    m_kr less a model of Jacobian ``design`` (n, p); e.g. |a_k| - g of the
    orientation-free fit): one wander variance (output units^2) common to
    the channels, its correlation time shared, by REML over a grid, where
    the generalised Q rejects the model's covariance."""
    n, p = design.shape
    if n - p < 1:
        return between
    base = between.projected(h)
    x = np.linalg.svd(design, full_matrices=False)[0][:, : np.linalg.matrix_rank(design)]
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    if generalised_q(residuals, base, x) <= chdtri(n - x.shape[1], SIGNIFICANCE) and between.modelled.all():
        return between
    taus, lag, since = _taus(between)
    spread = float(np.mean(np.einsum("rkk->rk", between.channels)))
    grid = np.r_[0.0, np.geomspace(1e-4, 1e4, VARIANCE_GRID - 1) * max(spread, 1e-300)]
    best: tuple[float, float, np.ndarray] = (-np.inf, taus[0], np.zeros(grid.size))
    for tau in taus:
        corr = _correlation(tau, lag, since)
        ll = restricted_loglik(residuals, base, (h @ h.T) * corr, grid, x)
        if ll.max() > best[0]:
            best = (float(ll.max()), float(tau), ll)
    _, tau, ll = best
    slower = float(np.ptp(between.t_mid_s)) <= tau < np.inf
    # chi^2(1) 95 %: 3.84 / 2 below the profile's top
    s2 = grid[np.flatnonzero(ll >= ll.max() - 1.92).max()] if slower or not between.modelled.all() else grid[np.argmax(ll)]
    corr = _correlation(tau, lag, since)
    note = between.note or (SLOWER_THAN_RECORD if slower and s2 > 0 else None)
    return replace(between, channels=between.channels + s2 * corr[None], note=note)
