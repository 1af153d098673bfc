"""Pose means under the recording's noise model: the covariance of each
pose's mean and the part every pose shares.

A noise correlated over longer than a pose (a Gauss-Markov wander, a
flicker floor) moves a pose's mean as a whole, which its own scatter
cannot show, and moves poses far apart alike. Where the poses' residuals
are correlated from sample to sample (``fit.correlated``), each channel's
noise model is identified from them (``rotcal.noise``: the Allan variance
of the pose residuals fitted with the IEEE Std 952 terms, ``noise.means``
taking the slow terms only where the data show them), and the covariance
V of the poses' means under it (``noise.means.window_mean_covariance``,
flicker down to the record's length) is split into a part c_r common to
every pose, the mean of V's off-diagonal elements, and each pose's own
V_kk - c_r. With equal weights that split gives the mean of all poses
exactly the variance 1' V 1 / n^2; a common shift of every pose's mean is
taken up by the offset O alone (the static models are invariant to
m -> m + d, O -> O + d), so the static fits carry c as a Type A input to O
(``shared_offset_covariance``) and the pose's own part in ``cov_mean``.

Each pose's own part is at least its white scatter's s^2 / n. Where the
noise is correlated but its model cannot be identified (poses too short
for the Allan variance to reach past the sample-to-sample correlation),
the lag-1/lag-2 widening stays and the shared part is NaN: the static
fits then say that a wander common to the poses is not in u.
"""

from __future__ import annotations

import numpy as np
import polars as pl
from scipy.special import chdtri

from rotcal.fit.wander import SIGNIFICANCE, column_basis, generalised_q, wander_fit
from rotcal.model.physics import CHANNELS
from rotcal.model.results import whole_fit_input
from rotcal.noise.allan import pooled_avars
from rotcal.noise.means import process_of, window_mean_covariance
from rotcal.noise.model import identify_channel

SHARED_NOT_MODELLED = ("the pose noise is correlated but its model could not be identified from the poses (too short for "
                       "the Allan variance): each pose mean's u holds its lag-1/lag-2 widening, and a wander common to "
                       "every pose, which moves the offsets, is not in u")


def pose_noise_covariance(t_ns: np.ndarray, y: np.ndarray, group: np.ndarray, n_groups: int, means: np.ndarray,
                          cov_white: np.ndarray, cov_widened: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(covariance of each pose's own mean (G, 3, 3), the covariance every
    pose's mean shares (3, 3)) under the noise model of the pose residuals
    ``y - means[group]`` (module docstring); ``cov_white`` the scatter's
    s^2 / n, ``cov_widened`` with the lag-1/lag-2 widening (returned with a
    NaN shared part where no channel could be modelled)."""
    inside = np.flatnonzero(group >= 0)
    unmodelled = (cov_widened, np.full((3, 3), np.nan))
    if inside.size < 2 or n_groups < 2:
        return unmodelled
    t_s = t_ns.astype(np.int64) / 1e9
    dt = float(np.median(np.diff(t_s[inside])))
    if not dt > 0:
        return unmodelled
    g = group[inside]
    # each pose's contiguous runs of samples: a pause (a dropped sample run) splits a piece
    cut = np.flatnonzero((np.diff(g) != 0) | (np.diff(t_s[inside]) > 1.5 * dt)) + 1
    resid = y[inside] - means[g]
    pieces = [p for p in np.split(resid, cut) if p.shape[0] >= 2]
    if not pieces:
        return unmodelled
    allan = pooled_avars(pieces, 1 / dt)
    first = np.full(n_groups, np.inf)
    last = np.full(n_groups, -np.inf)
    np.minimum.at(first, g, t_s[inside])
    np.maximum.at(last, g, t_s[inside])
    if not np.all(np.isfinite(first)):  # an empty group: no window to take a mean over
        return unmodelled
    record = (float(first.min()), float(last.max()) + dt)
    own = np.einsum("kii->ki", cov_white).copy()
    shared = np.zeros(3)
    modelled = np.zeros(3, bool)
    for r, c in enumerate(CHANNELS):
        channel = identify_channel(c, [p[:, r] for p in pieces], 1 / dt, "", allan[r])
        if channel.reason:
            continue
        v = window_mean_covariance(process_of(channel), first, last + dt, dt, record)
        off = v[~np.eye(n_groups, dtype=bool)]
        shared[r] = max(float(off.mean()), 0.0)
        own[:, r] = np.maximum(np.diag(v) - shared[r], own[:, r])
        modelled[r] = True
    if not modelled.any():
        return unmodelled
    # each channel's own variance from the model, the channels' correlation from the scatter
    white_diag = np.einsum("kii->ki", cov_white)
    scale = np.where(modelled, np.sqrt(np.divide(own, white_diag, out=np.ones_like(own), where=white_diag > 0)),
                     np.sqrt(np.divide(np.einsum("kii->ki", cov_widened), white_diag, out=np.ones_like(own),
                                       where=white_diag > 0)))
    return cov_white * scale[:, :, None] * scale[:, None, :], np.diag(shared)


def pose_wander(c: np.ndarray, var: np.ndarray, poses: pl.DataFrame, x: np.ndarray, seen: str = "references"
                ) -> np.ndarray | None:
    """The wander the pose means' scatter shows beyond their noise, the
    part every pose shares: per column of ``c`` (poses, k: the means, or a
    fit's residuals) of variances ``var`` (poses, k) under fixed effects
    ``x`` (poses, p), the generalised Cochran's Q test and the first-order
    Gauss-Markov wander's restricted maximum likelihood of ``fit.wander``
    over the poses' mid-times (its upper 95 % bound where tau is longer
    than the session, which cannot tell it from the offset), and the part
    of it every pose shares (k,): a random walk's mean covariance between
    poses, a Gauss-Markov wander's variance (``seen = "magnitudes"``, the
    orientation-free fit's: the largest variance either way); None where
    the scatter shows none or the poses carry no times."""
    if (poses.height < 3 or not {"t_start_ns", "t_end_ns"} <= set(poses.columns)
            or poses["t_start_ns"].null_count() or poses["t_end_ns"].null_count()):
        return None
    start = poses["t_start_ns"].to_numpy() / 1e9
    stop = poses["t_end_ns"].to_numpy() / 1e9
    t, duration = (start + stop) / 2, np.maximum(stop - start, 1e-9)
    basis = column_basis(x)
    dof = len(t) - basis.shape[1]
    var = np.maximum(var, np.max(var) * 1e-12)
    if dof < 1 or not np.all(np.isfinite(c)) or not np.all(var > 0):
        return None
    c = c - basis @ (basis.T @ c)  # the scatter beyond the fixed effects (REML's own projection takes the rest)
    base = [np.diag(var[:, r]) for r in range(c.shape[1])]
    q = np.array([generalised_q(c[:, r], base[r], basis) for r in range(c.shape[1])])
    if not np.any(q > chdtri(dof, SIGNIFICANCE)) and not q.sum() > chdtri(q.size * dof, SIGNIFICANCE):
        return None
    span = float(t.max() - t.min())
    since = t - float(np.min(start))
    s2, upper, tau = wander_fit(c, base, t, (float(np.min(duration)) / 2, 10 * max(span, 1e-9)), basis, since)
    if np.isinf(tau):
        corr = np.minimum.outer(since, since) / max(float(since.max()), 1e-9)
    else:
        corr = np.exp(-np.abs(t[:, None] - t[None, :]) / tau)
    s2 = upper if span <= tau else s2
    if seen == "magnitudes" or not np.isinf(tau):
        # a Gauss-Markov wander's time constant is poorly determined by a few tens of poses, and the part they share
        # lies between 0 and its variance: its variance, conservatively; the magnitudes (which the directions and
        # nine parameters largely take up) size a random walk no better
        return s2 * float(np.max(np.diag(corr)))
    off = corr[~np.eye(len(t), dtype=bool)]
    return s2 * float(off.mean())  # a random walk's covariance from the session's start, fixed by its form


def with_shared(poses: pl.DataFrame, parts: list, wander: np.ndarray | None = None) -> list:
    """A static fit's budget ``parts`` (input, state covariance) with the
    noise every pose shares as Type A inputs to the offsets: the noise
    model's (``cov_shared``, none where the poses carry none or it was not
    identified) and the pose means' scatter's ``wander`` (per channel)."""
    shared = shared_offset_covariance(poses)
    out = list(parts)
    if shared is not None and np.all(np.isfinite(shared)):
        out.append((whole_fit_input("pose noise shared by every pose", float("inf")), shared))
    if wander is not None and np.any(wander > 0):
        cov = np.zeros((12, 12))
        cov[9:, 9:] = np.diag(wander)
        out.append((whole_fit_input("pose means' wander shared by every pose", float("inf")), cov))
    return out


def shared_unidentified(poses: pl.DataFrame) -> bool:
    """Whether the poses' noise is correlated but its model was not identified (``SHARED_NOT_MODELLED``)."""
    return "cov_shared" in poses.columns and poses.height > 0 and bool(np.isnan(poses["cov_shared"][0].to_numpy()).any())


def shared_offset_covariance(poses: pl.DataFrame) -> np.ndarray | None:
    """The covariance (12, 12) of a static result's state (g L or C rows,
    then O) from the noise every pose's mean shares (``cov_shared``): on
    the offsets alone, a common shift of the means being an offset's; None
    where the poses carry none, NaN where it was not identified."""
    if "cov_shared" not in poses.columns or poses.height == 0:
        return None
    shared = np.array(poses["cov_shared"][0], float).reshape(3, 3)
    if np.all(shared == 0):
        return None
    out = np.zeros((12, 12))
    out[9:, 9:] = shared
    return out
