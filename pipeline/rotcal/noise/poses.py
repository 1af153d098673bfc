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
static model (``channel_wander`` with known references, ``scalar_wander``
from |a| - g without): a first-order Gauss-Markov wander, or a random walk
from the record's start, where the generalised Cochran's Q of the
residuals rejects the model's covariance at ``SIGNIFICANCE``, its
correlation time and variance averaged by their restricted likelihood
(``averaged_wander``); the reductions then weigh the poses by generalised
least squares with the full covariance, so the offsets carry the wander
every pose shares.

Where a channel's model cannot be identified (poses too short for five
averaging times), its poses keep their own covariance (the lag widening of
``fit.means``), the wander is measured from the scatter whatever the test
says, and the note says so; where the model misses its own Allan variance
(reduced chi-square beyond ``MISFIT``), each pose's own variance is its
floor.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rotcal.fit.wander import generalised_q, restricted_loglik
from rotcal.noise.allan import pooled_avars
from rotcal.noise.means import short_record_process, window_mean_covariance
from rotcal.noise.model import identify_channel
from rotcal.noise.residuals import split_at_pauses

UNMODELLED = ("the poses are too short to identify the noise model of channel(s) {channels} (fewer than five averaging "
              "times): their means keep their own scatter's variance, and a wander between poses rests on their scatter "
              "about the model alone")
# the wander test's level: a pose fit's few residual degrees of freedom (15 for 24 poses without references)
# leave a wander that moves the offsets by several u at p of 0.01 to 0.02 (docs/measured.md)
SIGNIFICANCE = 0.05
# correlation times up to twice the poses' span; slower ones the random walk from the record's start stands for
TAU_SPANS = 2.0
TAU_GRID = 25
VARIANCE_GRID = 41
MISFIT = 3.0  # a noise model's reduced chi-square beyond it: the model misses its own Allan variance
# a pose's own variance beyond its independent samples' by this factor: ``fit.means`` widened it for a lag
# (its density ratio is at least 1.4 where applied), which the model replaces
LAG_WIDENED = 1.2


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
    plain: bool = False  # each pose's own variances, no covariance between poses: white noise as it was

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
    modelled, kept = np.zeros(3, bool), np.zeros(3, bool)
    # each pose's variance of its mean as independent samples give it (the lag widening's and rounding's base)
    plain = np.array([y[a:b].var(axis=0, ddof=1) / (b - a) if b - a > 1 else np.full(3, np.nan) for a, b in zip(starts, stops)])
    pieces = [p for a, b in zip(starts, stops) if b - a >= 2
              for p in split_at_pauses(t_ns[a:b], y[a:b] - y[a:b].mean(axis=0), dt)] if dt > 0 else []
    allan = pooled_avars(pieces, 1 / dt) if pieces else []
    for r in range(3):
        channels[r][np.diag_indices(n)] = own[:, r, r]
        kept[r] = True
        if not pieces:
            continue
        noise = identify_channel("", [p[:, r] for p in pieces], 1 / dt, "", allan[r])
        if noise.reason:
            continue
        modelled[r] = True
        process = short_record_process(noise, float(noise.allan.tau_s[-1]))
        if not (process.gauss_markov or process.flicker_b) and not np.any(own[:, r, r] > LAG_WIDENED * plain[:, r]):
            continue  # white, and no pose's scatter was widened for its lag: each pose's own variance, as it was
        kept[r] = False
        # a pose's Allan variance reaches a few seconds: the terms shorter than its longest averaging time
        # are a filter's or an autoregression's; a slower one enters only where the data show it
        # (``short_record_process``), the scatter between poses measures the rest (``channel_wander``)
        shown = window_mean_covariance(process, a0, a1, dt, record)
        if noise.chi2_reduced > MISFIT:  # a model that misses its own Allan variance: each pose's own scatter at least
            shown[np.diag_indices(n)] = np.maximum(np.diag(shown), own[:, r, r])
        channels[r] = shown
    missing = [c for c, ok in zip("uvw", modelled) if not ok]
    note = UNMODELLED.format(channels=", ".join(missing)) if missing else None
    return PoseCovariance(channels, (a0 + a1) / 2, a1 - a0, modelled, note, bool(kept.all()))


def with_pose_variances(cov: np.ndarray, between: PoseCovariance) -> np.ndarray:
    """The poses' own covariances (n, 3, 3) with each channel's variance
    that of ``between`` (its diagonal), the channels' correlations kept."""
    sd_own = np.sqrt(np.einsum("kii->ki", cov))
    sd = np.sqrt(np.einsum("rkk->kr", between.channels))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(sd_own > 0, sd / sd_own, 1.0)
    return cov * scale[:, :, None] * scale[:, None, :]


def _correlations(between: PoseCovariance) -> list[np.ndarray]:
    """The wander's correlation between poses for each correlation time of
    the grid: exp(-|t_k - t_l| / T) for T log-spaced from half the shortest
    pose to ``TAU_SPANS`` times the poses' span, and a random walk from the
    record's start (min(t_k, t_l) / max t; the grid's last), which a
    wander slower than the record resembles over it."""
    t = between.t_mid_s
    span = float(np.ptp(t)) if t.size else 0.0
    low = max(float(np.min(between.duration_s)) / 2, 1e-9) if t.size else 1.0
    lag = np.abs(t[:, None] - t[None, :])
    since = t - (t - between.duration_s / 2).min()
    walk = np.minimum.outer(since, since) / max(float(since.max()), 1e-9)
    return [np.exp(-lag / tau) for tau in np.geomspace(low, max(TAU_SPANS * span, 2 * low), TAU_GRID)] + [walk]


def averaged_wander(c: np.ndarray, base: np.ndarray, corrs: list[np.ndarray], spread: float, x: np.ndarray,
                    seen: list[np.ndarray] | None = None) -> np.ndarray:
    """The wander's covariance s^2 C_T (n, n) beside ``base`` that the
    residuals ``c`` (n,) about a model of fixed effects ``x`` (n, p,
    orthonormal columns) show, averaged over a grid of correlations
    ``corrs`` and variances s^2 (0, and log-spaced about ``spread``)
    weighted by the restricted likelihood (Patterson & Thompson 1971,
    ``fit.wander.restricted_loglik``): the posterior mean under priors flat
    in log T and log s^2. A record of a few poses pins neither well, and
    the offsets' variance grows with both: the average carries their
    uncertainty into u, where the single best pair understates it whenever
    it falls short. ``seen``: the correlations as the residuals see them
    (a projection of ``corrs``; default ``corrs``)."""
    grid = np.r_[0.0, np.geomspace(1e-4, 1e4, VARIANCE_GRID - 1) * max(spread, 1e-300)]
    ll = np.array([restricted_loglik(c, base, corr, grid, x) for corr in (corrs if seen is None else seen)])
    weight = np.exp(ll - ll.max())
    weight /= weight.sum()
    return sum((float(w @ grid) * corr for w, corr in zip(weight, corrs)), np.zeros(corrs[0].shape))


def channel_wander(between: PoseCovariance, residual_basis: np.ndarray, means: np.ndarray) -> PoseCovariance:
    """``between`` with each channel's wander beyond the noise model,
    measured from the pose means ``means`` (n, 3) about a model linear in
    ``residual_basis`` (n, p; e.g. the known references and 1) per channel
    (``averaged_wander``), where the generalised Q rejects the model's
    covariance at ``SIGNIFICANCE`` (per channel or pooled; always where the
    model is not identified)."""
    n, p = residual_basis.shape
    if n - p < 1:
        return between
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    q = np.array([generalised_q(means[:, r], between.channels[r], residual_basis) for r in range(3)])
    wanders = (q > chdtri(n - p, SIGNIFICANCE)) | (q.sum() > chdtri(3 * (n - p), SIGNIFICANCE)) | ~between.modelled
    if not wanders.any():
        return between
    corrs = _correlations(between)
    x = np.linalg.svd(residual_basis, full_matrices=False)[0]
    resid = means - x @ (x.T @ means)  # what the model leaves: REML sees only that, and it sizes the variance grid
    added = np.zeros_like(between.channels)
    for r in np.flatnonzero(wanders):
        spread = max(float(np.var(resid[:, r])), float(np.mean(np.diag(between.channels[r]))))
        added[r] = averaged_wander(resid[:, r], between.channels[r], corrs, spread, x)
    return replace(between, channels=between.channels + added)


def scalar_wander(between: PoseCovariance, residuals: np.ndarray, h: np.ndarray, design: np.ndarray) -> PoseCovariance:
    """``between`` with a wander beyond the noise model measured from
    scalar residuals of the pose means (``residuals`` (n,) = sum_r h_kr
    m_kr less a model of Jacobian ``design`` (n, p); e.g. |a_k| - g of the
    orientation-free fit, whose scalars show less of it than a labelled
    fit's three channels): one wander variance (output units^2) common to
    the channels (``averaged_wander``), where the generalised Q rejects the
    model's covariance at ``SIGNIFICANCE`` (always where the model is not
    identified)."""
    n, p = design.shape
    if n - p < 1:
        return between
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    base = between.projected(h)
    x = np.linalg.svd(design, full_matrices=False)[0][:, : np.linalg.matrix_rank(design)]
    if generalised_q(residuals, base, x) <= chdtri(n - x.shape[1], SIGNIFICANCE) and between.modelled.all():
        return between
    corrs = _correlations(between)
    spread = float(np.mean(np.einsum("rkk->rk", between.channels)))
    added = averaged_wander(residuals, base, corrs, spread, x, [(h @ h.T) * corr for corr in corrs])
    return replace(between, channels=between.channels + added[None])
