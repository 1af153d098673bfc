"""Pose means: each still interval's mean output and the covariance of
that mean, the fit of a constant to a still segment (GUM 4.2.3: the
experimental standard deviation of the mean), widened where the noise is
correlated from sample to sample (``fit.correlated``). The segmentation's
dwells and the static reductions' poses both summarise their samples here.

Under coloured noise (``modelled_pose_table``) each pose mean's variance
and the covariance between pose means come from the noise model of the
poses' residuals (``noise.poses``), and the wander beyond it from the
poses' scatter about the static model (``channel_wander``,
``scalar_wander``: ``fit.wander``'s restricted likelihood, as the table
segments' offsets measure it), which the static reductions weigh the poses
by (generalised least squares)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import polars as pl

from rotcal.fit.correlated import autoregressive_density_ratio, density_ratio
from rotcal.fit.quantization import mean_rounding_variance, output_step
from rotcal.fit.wander import OffsetCovariance, generalised_q, restricted_loglik
from rotcal.model.columns import Outputs, columns_of, selected_rows
from rotcal.model.physics import CHANNELS
from rotcal.noise.poses import PoseCovariance, pose_covariance, with_pose_variances
from rotcal.noise.residuals import split_at_pauses


def group_statistics(y: np.ndarray | Outputs, group: np.ndarray, n_groups: int
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per group: sample count, mean (G, 3) and covariance of the mean
    (G, 3, 3) of the rows of ``y`` (n, 3), or of its columns, labelled
    ``group`` (0 .. G-1; -1 = none).

    Where a group's samples are correlated from one to the next (lag-1
    autocorrelation significant and positive), the covariance is widened
    by the noise density's ratio to white at zero frequency
    (``fit.correlated``). A quantized output (its step found from the
    samples) adds the rounding's variance of a mean to the diagonal
    (``fit.quantization``): a pose of identical samples is uncertain by
    the step, not by the step over the square root of its count.
    """
    at = selected_rows(group >= 0)
    g, columns = group[at], [c[at] for c in columns_of(y)]
    counts = np.bincount(g, minlength=n_groups).astype(float)
    means = np.column_stack([np.bincount(g, weights=c, minlength=n_groups) for c in columns]) / counts[:, None]
    scatter, square, lag1, lag2 = _centred_sums(columns, g, means)
    with np.errstate(divide="ignore", invalid="ignore"):  # a one-sample group: NaN, refused by reduce_static
        cov = scatter / ((counts - 1.0) * counts)[:, None, None]
        rho = lag1 / square, lag2 / square  # as fit.correlated.grouped_autocorrelation (run: the group)
    # noise correlated from sample to sample: a mean's variance is the noise density at zero frequency
    widen = np.sqrt(density_ratio(*rho, counts[:, None], 0.0))
    cov = cov * widen[:, :, None] * widen[:, None, :]
    if g.size:
        # the output step's rounding, the same for every sample of a pose when the noise is below it
        # (each pose's own scatter: a pose dithering across a level boundary says nothing of the others)
        with np.errstate(divide="ignore", invalid="ignore"):
            sample_var = np.einsum("kii->ki", scatter) / (counts - 1.0)[:, None]
        diag = np.einsum("kii->ki", cov)
        diag += mean_rounding_variance(output_step(columns)[None], sample_var)
    return counts.astype(np.int64), means, cov


# the wander test's level: a pose fit's few residual degrees of freedom (15 for 24 poses without references)
# leave a wander that moves the offsets by several u at p of 0.01 to 0.02 (docs/measured.md)
SIGNIFICANCE = 0.05
SEGMENT_OFFSETS = "the means carry the noise model and wander of the table segments' offsets over the record"
# correlation times up to twice the poses' span; slower ones the random walk from the record's start stands for
TAU_SPANS = 2.0
TAU_GRID = 25
VARIANCE_GRID = 41
# samples a block of the centred sums: a block's products stay a few MB
SUM_BLOCK = 1 << 18


def _centred_sums(columns: list[np.ndarray], g: np.ndarray, means: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per group, of the samples less their group's mean: the sums of
    products of every two channels (G, 3, 3), of squares, and of products
    one and two samples apart in one group (G, 3 each). A block of samples
    at a time, each block's sums carried on from the last block's in the
    order one ``np.bincount`` over every sample adds them (its sums, bit
    for bit); a block reaches two samples back for the lagged products."""
    n_groups, width = means.shape
    pairs = [(i, j) for i in range(width) for j in range(width)]
    sums = np.zeros((len(pairs) + 3 * width, n_groups))
    carry = np.arange(n_groups)
    # many groups (a file of pose means, one sample each): one block, not the carried sums of every group per block
    block = SUM_BLOCK if n_groups <= SUM_BLOCK // 8 else max(g.size, 1)

    def add(k: int, where: np.ndarray, weights: np.ndarray) -> None:
        # each group's sum so far goes first (0 + s is s), then the block's weights in order
        sums[k] = np.bincount(np.concatenate([carry, where]), np.concatenate([sums[k], weights]), n_groups)

    for a in range(0, g.size, block):
        b = min(a + block, g.size)
        lo = max(a - 2, 0)
        gb = g[lo:b]
        centred = [np.subtract(c[lo:b], means[gb, r]) for r, c in enumerate(columns)]
        own = slice(a - lo, None)
        for k, (i, j) in enumerate(pairs):
            add(k, gb[own], centred[i][own] * centred[j][own])
        for r, c in enumerate(centred):
            add(len(pairs) + r, gb[own], c[own] ** 2)
            for lag in (1, 2):  # samples i - lag and i, from i = lag on, where both are in one group
                at = max(a, lag) - lo
                same = gb[at:] == gb[at - lag : gb.size - lag]
                add(len(pairs) + lag * width + r, gb[at:], np.where(same, c[at:] * c[at - lag : c.size - lag], 0.0))
    scatter = sums[: len(pairs)].T.reshape(n_groups, width, width)
    square, lag1, lag2 = (sums[len(pairs) + m * width : len(pairs) + (m + 1) * width].T for m in range(3))
    return scatter, square, lag1, lag2


def pose_table(t_ns: np.ndarray, y: np.ndarray | Outputs, starts: np.ndarray, stops: np.ndarray) -> pl.DataFrame:
    """Mean and covariance of the mean of each pose (samples ``starts[k]:stops[k]``)."""
    starts, stops = np.asarray(starts, np.int64), np.asarray(stops, np.int64)
    group = np.full(t_ns.size, -1, np.int64)
    for k, (a, b) in enumerate(zip(starts, stops)):  # poses do not overlap; a few hundred slices, no n-long temporaries
        group[a:b] = k
    counts, means, cov = group_statistics(y, group, starts.size)
    return pl.DataFrame({
        "pose": np.arange(starts.size, dtype=np.int64), "t_start_ns": t_ns[starts], "t_end_ns": t_ns[stops - 1],
        "n_samples": counts, **{f"mean_{c}": means[:, r] for r, c in enumerate(CHANNELS)},
        "cov_mean": cov.reshape(-1, 9).tolist(),
    }, schema_overrides={"cov_mean": pl.List(pl.Float64)})



def with_noise_model(poses: pl.DataFrame, t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray, stops: np.ndarray
                     ) -> tuple[pl.DataFrame, PoseCovariance]:
    """The pose table ``poses`` of the samples ``starts[k]:stops[k]`` with
    each pose mean's variance from the noise model identified from the
    poses' residuals (``noise.poses``), and the covariance between the pose
    means that the static reductions weigh them by (generalised least
    squares)."""
    own = np.array(poses["cov_mean"].to_list(), float).reshape(-1, 3, 3)
    y, starts, stops = np.asarray(y, float), np.asarray(starts, np.int64), np.asarray(stops, np.int64)
    between = autoregressive_widening(pose_covariance(t_ns, y, starts, stops, own), t_ns, y, starts, stops)
    cov = with_pose_variances(own, between)
    return poses.with_columns(cov_mean=pl.Series(cov.reshape(-1, 9).tolist(), dtype=pl.List(pl.Float64))), between


def autoregressive_widening(between: PoseCovariance, t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray,
                            stops: np.ndarray) -> PoseCovariance:
    """``between`` with each pose mean's variance in the channels whose
    noise model the poses do not identify (``PoseCovariance.modelled``) and
    whose samples are correlated: the samples' variance over their count
    times the density ratio at zero frequency of the autoregression that
    describes the poses' pooled residuals
    (``fit.correlated.autoregressive_density_ratio``), in place of each
    pose's lag widening, plus the output step's rounding. A filter whose
    Allan variance no model of the catalogue's terms fits (a fourth-order
    low-pass at 0.05 of the rate) had its pose means' sd from the lag
    widening three times their true one (1.09 for 0.36 counts)."""
    if between.modelled.all() or t_ns.size < 2:
        return between
    dt = float(np.median(np.diff(t_ns))) / 1e9
    if dt <= 0:
        return between
    counts = (stops - starts).astype(float)
    sample_var = np.array([y[a:b].var(axis=0, ddof=1) if b - a > 1 else np.full(3, np.nan) for a, b in zip(starts, stops)])
    rounding = mean_rounding_variance(output_step([y[:, r] for r in range(3)])[None], sample_var)
    pieces = [p for a, b in zip(starts, stops) if b - a >= 2 for p in split_at_pauses(t_ns[a:b], y[a:b] - y[a:b].mean(axis=0), dt)]
    channels = between.channels.copy()
    for r in np.flatnonzero(~between.modelled):
        ratio = autoregressive_density_ratio([p[:, r] for p in pieces])
        widened = sample_var[:, r] / counts * ratio + rounding[:, r]
        diag = np.einsum("kk->k", channels[r])
        # where the lag widening applied (correlated samples); a pose too short for it keeps its own
        channels[r][np.diag_indices_from(channels[r])] = np.where(np.isfinite(widened) & (ratio > 1.0), widened, diag)
    return replace(between, channels=channels)


def modelled_pose_table(t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray, stops: np.ndarray
                        ) -> tuple[pl.DataFrame, PoseCovariance]:
    """``pose_table`` with the noise model's variances and covariance between poses (``with_noise_model``)."""
    return with_noise_model(pose_table(t_ns, y, starts, stops), t_ns, y, starts, stops)


def _correlations(between: PoseCovariance, within_span: bool = False) -> list[np.ndarray]:
    """The wander's correlation between poses for each correlation time of
    the grid: exp(-|t_k - t_l| / T) for T log-spaced from half the shortest
    pose to ``TAU_SPANS`` times the poses' span, and a random walk from the
    record's start (min(t_k, t_l) / max t; the grid's last), which a
    wander slower than the record resembles over it; ``within_span``: T up
    to the span alone (``channel_wander``'s slow terms)."""
    t = between.t_mid_s
    span = float(np.ptp(t)) if t.size else 0.0
    low = max(float(np.min(between.duration_s)) / 2, 1e-9) if t.size else 1.0
    lag = np.abs(t[:, None] - t[None, :])
    if within_span:
        return [np.exp(-lag / tau) for tau in np.geomspace(low, max(span, 2 * low), TAU_GRID)]
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
    covariance at ``SIGNIFICANCE`` (per channel or pooled). A channel whose
    model holds terms slower than a pose (``PoseCovariance.slow``: their
    size read from a pose's few seconds, their correlation time beyond
    what a pose shows) has them measured instead from the scatter, whatever
    Q says, with correlation times up to the poses' span: a slow term
    extrapolated from within poses takes them as nearly independent, and
    their common offset moved with the wander (the mix's 300 s term: O's sd
    of z 1.37 that way, 0.99 measured). A wander slower than the span is
    the offset for this record."""
    n, p = residual_basis.shape
    if n - p < 1:
        return between
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    q = np.array([generalised_q(means[:, r], between.channels[r], residual_basis) for r in range(3)])
    wanders = (q > chdtri(n - p, SIGNIFICANCE)) | (q.sum() > chdtri(3 * (n - p), SIGNIFICANCE))
    slow = np.zeros(3, bool) if between.slow is None else between.slow
    if not wanders.any() and not slow.any():
        return between
    x = np.linalg.svd(residual_basis, full_matrices=False)[0]
    resid = means - x @ (x.T @ means)  # what the model leaves: REML sees only that, and it sizes the variance grid
    channels = between.channels.copy()
    for r in np.flatnonzero(wanders | slow):
        base = between.fast[r] if slow[r] and between.fast is not None else between.channels[r]
        spread = max(float(np.var(resid[:, r])), float(np.mean(np.diag(base))))
        channels[r] = base + averaged_wander(resid[:, r], base, _correlations(between, bool(slow[r])), spread, x)
    return replace(between, channels=channels)


def scalar_wander(between: PoseCovariance, residuals: np.ndarray, h: np.ndarray, design: np.ndarray) -> PoseCovariance:
    """``between`` with a wander beyond the noise model measured from
    scalar residuals of the pose means (``residuals`` (n,) = sum_r h_kr
    m_kr less a model of Jacobian ``design`` (n, p); e.g. |a_k| - g of the
    orientation-free fit, whose scalars show less of it than a labelled
    fit's three channels): one wander variance (output units^2) common to
    the channels (``averaged_wander``), where the generalised Q rejects the
    model's covariance at ``SIGNIFICANCE``; where the model holds terms
    slower than a pose, measured in their place whatever Q says
    (``channel_wander``)."""
    n, p = design.shape
    if n - p < 1:
        return between
    from scipy.special import chdtri  # here: scipy's import would slow every CLI start

    slow = between.slow is not None and bool(between.slow.any())
    kept = replace(between, channels=between.fast) if slow and between.fast is not None else between
    base = kept.projected(h)
    x = np.linalg.svd(design, full_matrices=False)[0][:, : np.linalg.matrix_rank(design)]
    if not slow and generalised_q(residuals, base, x) <= chdtri(n - x.shape[1], SIGNIFICANCE):
        return between
    corrs = _correlations(between, slow)
    spread = float(np.mean(np.einsum("rkk->rk", kept.channels)))
    added = averaged_wander(residuals, base, corrs, spread, x, [(h @ h.T) * corr for corr in corrs])
    return replace(between, channels=kept.channels + added[None])


def with_segment_offsets(poses: pl.DataFrame, between: PoseCovariance, offsets: OffsetCovariance) -> tuple[pl.DataFrame, PoseCovariance]:
    """``poses`` (still intervals between a table recording's segments: an
    unlabelled recording's dwells) and their covariance ``between`` with
    what the segments' offsets showed over the whole record
    (``fit.wander.OffsetCovariance``): the recording's noise model, which
    the segments' long residuals identify where a pose's few seconds
    cannot (flicker to the record's length), and the wander the offsets'
    scatter shows beyond it. A pose's mean is an offset measured at its
    time as a segment's is, so it shares that wander; a random walk from
    the record's start then moves the poses' common offset as it moves
    the segments'."""
    # on the offsets' clock, the record's stamps in seconds (``fit.segments``); a sample stands for its interval
    start, stop = (poses[c].to_numpy() / 1e9 for c in ("t_start_ns", "t_end_ns"))
    dt = float(np.median((stop - start) / np.maximum(poses["n_samples"].to_numpy() - 1, 1)))
    channels = np.stack(offsets.channels(start - dt / 2, stop + dt / 2, list(between.channels)))
    # the segments' model in place of the poses' slow terms (``channel_wander`` would measure them from the scatter)
    wandering = replace(between, channels=channels, plain=False, fast=None, slow=None,
                        note="; ".join(filter(None, [between.note, SEGMENT_OFFSETS])))
    own = np.array(poses["cov_mean"].to_list(), float).reshape(-1, 3, 3)
    cov = with_pose_variances(own, wandering)
    return poses.with_columns(cov_mean=pl.Series(cov.reshape(-1, 9).tolist(), dtype=pl.List(pl.Float64))), wandering


def modelled_poses(samples: pl.DataFrame, poses: pl.DataFrame) -> tuple[pl.DataFrame, PoseCovariance | None]:
    """``with_noise_model`` of a recording's pose table (still intervals,
    labelled poses: ``combine.poses``), each pose the run of samples from
    its first to its last time stamp; ``poses`` as they are and None where
    a pose's mean has no variance in some channel (identical samples: no
    noise to model), the samples' time stamps do not increase or a pose's
    run holds other samples than its own (its count differs)."""
    t_all = samples["t_ns"].to_numpy()
    variances = np.array(poses["cov_mean"].to_list(), float).reshape(-1, 9)[:, [0, 4, 8]]
    if (poses.height < 2 or poses["t_start_ns"].null_count() or not np.all(variances > 0) or t_all.size < 2
            or not np.all(np.diff(t_all) > 0)):
        return poses, None
    first = np.searchsorted(t_all, poses["t_start_ns"].to_numpy(), "left")
    last = np.searchsorted(t_all, poses["t_end_ns"].to_numpy(), "right")
    if not np.array_equal(last - first, poses["n_samples"].to_numpy()) or np.any(first[1:] < last[:-1]):
        return poses, None
    # the poses' rows alone, one after another (a long recording's moves and table segments are not copied)
    rows = np.concatenate([np.arange(a, b) for a, b in zip(first, last)])
    stops = np.cumsum(last - first)
    y = samples.select(CHANNELS).to_numpy()[rows] if rows.size == samples.height else \
        samples.select(CHANNELS)[rows].to_numpy()
    return with_noise_model(poses, t_all[rows], y, stops - (last - first), stops)
