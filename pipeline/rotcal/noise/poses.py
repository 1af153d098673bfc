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
static model (``fit.means.channel_wander`` with known references,
``fit.means.scalar_wander`` from |a| - g without): a first-order Gauss-Markov wander, or a random walk
from the record's start, where the generalised Cochran's Q of the
residuals rejects the model's covariance at ``SIGNIFICANCE`` (and in place
of the model's terms slower than a pose wherever it holds them: a pose's
few seconds give their size poorly and their correlation time not at
all, ``PoseCovariance.fast``), its
correlation time and variance averaged by their restricted likelihood
(``fit.means.averaged_wander``); the reductions then weigh the poses by generalised
least squares with the full covariance, so the offsets carry the wander
every pose shares.

Where a channel's model cannot be identified (poses too short for five
averaging times), its poses keep their own covariance (the lag widening of
``fit.means``), a wander is added where their scatter shows one (as where
the model is identified: at a few residual degrees of freedom the scatter
alone sizes a wander poorly, ten poses of a nine-parameter fit gave s_w
0.4 % for 0.02 %), and the note says so; so too where the model misses its
own Allan variance (reduced chi-square beyond ``MISFIT``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from rotcal.noise.allan import pooled_avars
from rotcal.noise.means import short_record_process, window_mean_covariance
from rotcal.noise.model import identify_channel
from rotcal.noise.residuals import split_at_pauses

UNMODELLED = ("the poses do not identify the noise model of channel(s) {channels} (fewer than five averaging times, or "
              "no model of the catalogue's terms fits their Allan variance): their means keep their own scatter's variance (its lag widening)")
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
    # per channel, the covariance without the model's terms slower than a pose (``slow``: the channels that had
    # any); their size and correlation time the poses' scatter measures (``fit.means.channel_wander``)
    fast: np.ndarray | None = None
    slow: np.ndarray | None = None

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
    fast, slow = channels.copy(), np.zeros(3, bool)
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
        if noise.reason or noise.chi2_reduced > MISFIT:
            # a model that misses its own Allan variance (a filter's hump read as flicker: pose means of 3 s
            # under a low-pass at 0.1 of the rate came out with 6 counts for 0.5) is no model of the means
            continue
        modelled[r] = True
        process = short_record_process(noise, float(noise.allan.tau_s[-1]))
        if not (process.gauss_markov or process.flicker_b) and not np.any(own[:, r, r] > LAG_WIDENED * plain[:, r]):
            continue  # white, and no pose's scatter was widened for its lag: each pose's own variance, as it was
        kept[r] = False
        # a pose's Allan variance reaches a few seconds: the terms shorter than its longest averaging time
        # are a filter's or an autoregression's; a slower one enters only where the data show it
        # (``short_record_process``), the scatter between poses measures the rest (``fit.means.channel_wander``)
        channels[r] = window_mean_covariance(process, a0, a1, dt, record)
        longest = float(noise.allan.tau_s[-1])
        quick = replace(process, gauss_markov=tuple(t for t in process.gauss_markov if t[0] < longest), flicker_b=0.0)
        if quick != process:
            fast[r], slow[r] = window_mean_covariance(quick, a0, a1, dt, record), True
    missing = [c for c, ok in zip("uvw", modelled) if not ok]
    note = UNMODELLED.format(channels=", ".join(missing)) if missing else None
    fast = np.where(slow[:, None, None], fast, channels)
    return PoseCovariance(channels, (a0 + a1) / 2, a1 - a0, modelled, note, bool(kept.all()),
                          fast if slow.any() else None, slow if slow.any() else None)


def with_pose_variances(cov: np.ndarray, between: PoseCovariance) -> np.ndarray:
    """The poses' own covariances (n, 3, 3) with each channel's variance
    that of ``between`` (its diagonal), the channels' correlations kept."""
    sd_own = np.sqrt(np.einsum("kii->ki", cov))
    sd = np.sqrt(np.einsum("rkk->kr", between.channels))
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(sd_own > 0, sd / sd_own, 1.0)
    return cov * scale[:, :, None] * scale[:, None, :]
