"""Blind segmentation: static dwells, constant rotations and transitions of a
recording that carries nothing but ``t, u, v, w``.

1. Dwells: the stillness detector (``rotcal.segment.stillness``); each dwell's
   edges are then refined against its own mean.
2. Rotations: the DUT's outputs, offset-free and normalised by a rough
   ellipsoid fit, point along gravity; the angular rate of that direction
   (summed cross products of consecutive directions over a window, so that
   noise cancels and no angle wraps) is constant in magnitude and axis
   during a constant rotation and changes in a ramp or a hand move. A run
   of windows whose rate and axis agree with their neighbours' is a
   candidate; its rate comes from the spectrum and a four-parameter fit
   (``rotcal.fit.sinefit``), and its edges from that fit.
3. Edges: outward from a segment's core, the first sample from which the
   normalised squared residuals of the core's model keep exceeding their
   expectation (the minimum of the cumulative sum of ``z - kappa``, a CUSUM
   change point).
4. Axis: the offset-free output vector of a rotation moves in the plane
   spanned by the fitted sine and cosine vectors ``A`` and ``B``; its normal
   ``A x B`` is the table axis seen through the DUT. rotcal names the axis
   after the channel that normal is closest to (the DUT is mounted roughly
   aligned: u along x, v along y, w along z) and reports the angle between
   them.
5. Step sequences: consecutive dwells joined by moves that stay in the plane
   through the offset of the two dwells' outputs, about one common axis,
   form a static step sequence (its axis from the plane of its dwell means);
   a move faster than one sample (the output jumps between two consecutive
   samples) has no samples to stray from that plane and joins its dwells on
   their means alone. A time gap between two dwells (the logger paused; the
   move, perhaps a hand's, unseen) joins nothing. A chain is a table's step
   sequence only with the evidence of a table (``table_steps``): its
   directions on one great circle, turned by equal steps. Other dwells are
   single poses of unknown orientation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from rotcal.fit.sinefit import SineFit, fit_sine
from rotcal.model.columns import Outputs, sample_step, steps_over
from rotcal.model.physics import AXES
from rotcal.segment.motion import Motion, runs_of
from rotcal.segment.stillness import StillnessConfig, still_and_short


@dataclass(frozen=True)
class BlindConfig:
    stillness: StillnessConfig = field(default_factory=StillnessConfig)
    window_s: float = 2.0              # window of the angular-rate estimate
    rate_tolerance: float = 0.03       # steady: neighbouring windows' rates agree to this fraction...
    noise_sigmas: float = 6.0          # ...plus this many standard deviations of the rate's noise
    axis_tolerance_deg: float = 3.0    # steady: neighbouring windows' axes agree to this angle
    min_rotation_s: float = 10.0       # a constant rotation lasts at least this long...
    min_turns: float = 1.0             # ...and turns at least this many times
    max_residual_ratio: float = 5.0    # larger residuals (in noise sd) than this: not a constant rotation
    cusum_kappa: float = 2.5           # edge detection: CUSUM reference (z is 1 on average under the model)
    plane_tolerance_deg: float = 2.0   # a step move stays this close to its plane
    min_steps: int = 3                 # dwells in a step sequence
    step_tolerance_deg: float = 1.0    # a table's steps are equal to this angle (a hand's are not)


@dataclass(frozen=True, eq=False)
class Rotation:
    """A constant rotation: samples ``start:stop``, its fit, the table axis
    it was named after and the angle between that channel and the rotation
    normal, and the residual variance in units of the noise."""

    start: int
    stop: int
    fit: SineFit
    axis: str
    axis_offset_deg: float
    chi2_reduced: float


@dataclass(frozen=True, eq=False)
class StepSequence:
    """Dwells (indices into ``BlindSegmentation.dwells``) joined by moves about one axis."""

    dwells: tuple[int, ...]
    axis: str
    axis_offset_deg: float


@dataclass(frozen=True, eq=False)
class BlindSegmentation:
    """What the signals say: rotations, dwells (rows ``start, stop``), step
    sequences among the dwells, and the noise standard deviation per channel."""

    rotations: tuple[Rotation, ...]
    dwells: np.ndarray
    sequences: tuple[StepSequence, ...]
    noise_sd: np.ndarray
    offset: np.ndarray
    hand_chains: int = 0  # chains of dwells about one axis without a table's evidence (``table_steps``): poses
    short: pl.DataFrame | None = None  # the stillness detector's rejections (``still_and_short``)


def axis_from_normal(normal: np.ndarray) -> tuple[str, float]:
    """The table axis named after the channel closest to ``normal``, and the angle between them (deg)."""
    unit = np.abs(normal) / np.linalg.norm(normal)
    k = int(np.argmax(unit))
    return AXES[k], float(np.degrees(np.arccos(np.clip(unit[k], -1.0, 1.0))))


def rough_calibration(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Offset and a linear map that make the outputs ``y`` (samples that
    mostly measure gravity) unit vectors, only for finding directions (the
    calibration proper is elsewhere): an algebraic ellipsoid fit; where the
    samples lie in one plane (rotation about one table axis: gravity on one
    great circle) a circle fit in that plane, whose centre is the sphere's;
    otherwise a sphere fit."""
    centre = np.median(y, axis=0)
    scale = float(np.median(np.linalg.norm(y - centre, axis=1))) or 1.0
    m = (y - centre) / scale
    spread, basis = np.linalg.eigh(np.cov(m.T))
    if spread[0] < 1e-3 * spread[2]:
        plane = m @ basis[:, 1:]
        sol, *_ = np.linalg.lstsq(np.column_stack([2 * plane, np.ones(len(m))]), (plane**2).sum(axis=1), rcond=None)
        radius = np.sqrt(max(sol[2] + sol[:2] @ sol[:2], 1e-12))
        offset = basis[:, 1:] @ sol[:2] + float(m.mean(axis=0) @ basis[:, 0]) * basis[:, 0]
        return centre + scale * offset, np.eye(3) / (scale * radius)
    a, b, c = m.T
    design = np.column_stack([a * a, b * b, c * c, 2 * a * b, 2 * a * c, 2 * b * c, 2 * a, 2 * b, 2 * c])
    coef, *_ = np.linalg.lstsq(design, np.ones(len(m)), rcond=None)
    quad = np.array([[coef[0], coef[3], coef[4]], [coef[3], coef[1], coef[5]], [coef[4], coef[5], coef[2]]])
    sv = np.linalg.svd(design, compute_uv=False)
    if sv[-1] > 1e-6 * sv[0] and np.all(np.linalg.eigvalsh(quad) > 0):
        offset = -np.linalg.solve(quad, coef[6:])
        shape = quad / (1.0 + offset @ quad @ offset)
        return centre + scale * offset, np.linalg.cholesky(shape).T / scale
    sol, *_ = np.linalg.lstsq(np.column_stack([2 * m, np.ones(len(m))]), (m * m).sum(axis=1), rcond=None)
    radius = np.sqrt(max(sol[3] + sol[:3] @ sol[:3], 1e-12))
    return centre + scale * sol[:3], np.eye(3) / (scale * radius)


def _cusum_extent(z: np.ndarray, kappa: float) -> int:
    """How many of the samples ``z`` (ordered outward from a core) still
    belong to it: the minimum of the cumulative sum of z - kappa."""
    if z.size == 0:
        return 0
    return int(np.argmin(np.r_[0.0, np.cumsum(z - kappa)]))


def _extend(start: int, stop: int, low: int, high: int, z_of, kappa: float) -> tuple[int, int]:
    """Edges of the core ``start:stop`` moved outward (at most to ``low`` and
    ``high``) as far as the core's model still explains the samples."""
    left = _cusum_extent(z_of(np.arange(start - 1, low - 1, -1)), kappa)
    right = _cusum_extent(z_of(np.arange(stop, high)), kappa)
    return start - left, stop + right


def _bridge(runs: np.ndarray, motion: Motion, mid: np.ndarray, in_dwell: np.ndarray, max_hole: int,
            config: BlindConfig) -> np.ndarray:
    """Steady runs joined across short holes without a dwell when the rate
    and axis on both sides agree (one bad sample, or a burst of noise, does
    not end a rotation; a ramp between two rates does)."""
    if len(runs) < 2:
        return runs
    out = [runs[0].copy()]
    cos_tol = np.cos(np.deg2rad(config.axis_tolerance_deg))
    for s, e in runs[1:]:
        ps, pe = out[-1]
        f_prev, f_next = np.nanmedian(mid[motion.at(ps, pe)]), np.nanmedian(mid[motion.at(s, e)])
        same = (s - pe <= max_hole and not in_dwell[pe:s].any()
                and abs(f_next - f_prev) <= config.rate_tolerance * max(f_prev, f_next)
                and abs(motion.axis(pe - 1)[1] @ motion.axis(s)[0]) >= cos_tol)
        if same:
            out[-1][1] = e
        else:
            out.append(np.array([s, e]))
    return np.array(out)


def _sequences(y: Outputs, dwells: np.ndarray, means: np.ndarray, offset: np.ndarray, move: np.ndarray,
               recorded: np.ndarray, config: BlindConfig) -> tuple[tuple[StepSequence, ...], int]:
    """Step sequences: chains of dwells linked by in-plane moves about one
    axis (``move`` marks the samples that may belong to a move: not those of
    a constant rotation; ``recorded`` the consecutive dwells with no time gap
    between them: the move, if any, is in the samples)."""
    k = len(dwells)
    if k < config.min_steps:
        return (), 0
    a = means - offset
    normal = np.cross(a[:-1], a[1:])
    size = np.linalg.norm(normal, axis=1)
    normal = normal / np.where(size > 0, size, 1.0)[:, None]
    sin_tol = np.sin(np.deg2rad(config.plane_tolerance_deg))
    linked = size > sin_tol * np.linalg.norm(a[:-1], axis=1) * np.linalg.norm(a[1:], axis=1)
    for j in np.flatnonzero(linked):
        between = slice(dwells[j, 1], dwells[j + 1, 0])
        path = y.rows(between) - offset
        if not recorded[j] or not path.size or not move[between].all():
            # no sample between two dwells with no time gap: a move faster than a sample
            linked[j] = recorded[j] and not path.size
            continue
        linked[j] = bool((np.abs(path @ normal[j]) / np.linalg.norm(path, axis=1)).max() < sin_tol)
    same_axis = np.abs(np.einsum("ij,ij->i", normal[:-1], normal[1:])) > np.cos(np.deg2rad(config.axis_tolerance_deg))
    # chains of links: a new chain starts at a link that does not continue the previous one
    chain_start = linked & ~np.r_[False, linked[:-1] & linked[1:] & same_axis]
    chain = np.where(linked, np.cumsum(chain_start) - 1, -1)
    owner = np.full(k, -1)
    length = np.bincount(chain[chain >= 0]) if np.any(chain >= 0) else np.zeros(0, int)
    # a dwell shared by two chains goes to the longer one
    for j in np.argsort(-length[chain[linked]], kind="stable"):
        link = np.flatnonzero(linked)[j]
        for d in (link, link + 1):
            if owner[d] < 0:
                owner[d] = chain[link]
    out, hand = [], 0
    for c in np.unique(owner[owner >= 0]):
        members = np.flatnonzero(owner == c)
        if members.size < config.min_steps:
            continue
        plane_normal = np.linalg.svd(a[members], full_matrices=False)[2][-1]
        if not table_steps(a[members], plane_normal, config):
            hand += 1  # poses turned about one axis by hand: single poses of unknown orientation
            continue
        axis, off = axis_from_normal(plane_normal)
        out.append(StepSequence(tuple(int(m) for m in members), axis, off))
    return tuple(out), hand


def table_steps(outputs: np.ndarray, normal: np.ndarray, config: BlindConfig) -> bool:
    """Whether dwells' offset-free outputs (k, 3) are the steps a table
    makes: their directions on one great circle about ``normal`` (each
    within ``plane_tolerance_deg`` of its plane) and turned by equal steps
    (each within ``step_tolerance_deg`` of their median; three steps at
    least, two being equal by chance too often). A hand turning a
    DUT about one axis leaves both: irregular angles and a few degrees of
    wobble."""
    unit = outputs / np.linalg.norm(outputs, axis=1)[:, None]
    if np.degrees(np.arcsin(np.clip(np.abs(unit @ normal), 0.0, 1.0))).max() > config.plane_tolerance_deg:
        return False
    steps = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", unit[:-1], unit[1:]), -1.0, 1.0)))
    # two equal steps happen by chance; three or more are a table's program
    return steps.size >= 3 and bool(np.abs(steps - np.median(steps)).max() <= config.step_tolerance_deg)


def segment_blind(t_ns: np.ndarray, y: np.ndarray | Outputs, config: BlindConfig = BlindConfig()) -> BlindSegmentation:
    """Segment one capture's samples (time order) by their signals alone
    (``y``: (n, 3), or its columns)."""
    n = t_ns.size
    y = Outputs.of(y)
    dt_ns = sample_step(t_ns) if n > 1 else 1e9
    still, short = still_and_short(t_ns, y, config.stillness, dt_ns)
    raw = still.select("start", "stop").to_numpy().reshape(-1, 2)
    # a still interval reaches up to a window into the moves on either side: its core does not
    w_still = max(3, int(round(config.stillness.window_s * 1e9 / dt_ns)))
    margin = np.minimum(w_still, (raw[:, 1] - raw[:, 0]) // 3)
    cores = np.column_stack([raw[:, 0] + margin, raw[:, 1] - margin])
    noise_sd = noise_sd_of(y, cores)
    var = noise_sd**2

    # dwells: edges refined against each dwell's own mean; a dwell starts
    # no earlier than the previous one ends (both may explain the few samples
    # between two still intervals when the DUT barely moved)
    found: list[tuple[int, int]] = []
    for j, (s, e) in enumerate(cores):
        mean = y.mean(s, e)
        low = max(raw[j - 1, 1] if j else 0, found[-1][1] if found else 0, raw[j, 0] - w_still)
        high = min(raw[j + 1, 0] if j + 1 < len(raw) else n, raw[j, 1] + w_still)
        found.append(_extend(s, e, low, high, lambda i, m=mean: ((y.rows(i) - m) ** 2 / var).mean(axis=1),
                              config.cusum_kappa))
    dwells = np.array(found, dtype=np.int64).reshape(-1, 2)
    means = np.array([y.mean(s, e) for s, e in dwells]).reshape(-1, 3)

    sample = y.rows(slice(None, None, max(1, n // 20000)))
    offset, to_unit = rough_calibration(means if len(means) >= 12 else sample)
    window = max(3, int(round(config.window_s * 1e9 / dt_ns)))
    in_dwell = np.zeros(n, bool)
    for s, e in dwells:
        in_dwell[s:e] = True
    motion = Motion(t_ns, y, offset, to_unit, in_dwell, window, dt_ns)
    # the rate's noise: typical change between neighbouring windows where the DUT moves
    # (mostly steady rotation; ramps and hand moves are the minority that the median ignores)
    change = np.abs(motion.rate[1] - motion.rate[0])
    rate_noise = 1.4826 * float(np.nanmedian(change)) if np.any(np.isfinite(change)) else 0.0
    mid = np.nanmean(motion.rate, axis=0) if motion.pos.size else np.zeros(0)
    steady = np.zeros(n, bool)
    steady[motion.pos] = ((change <= config.rate_tolerance * mid + config.noise_sigmas * rate_noise)
                          & (motion.alignment >= np.cos(np.deg2rad(config.axis_tolerance_deg))))
    rotations = []
    candidates = _bridge(runs_of(steady), motion, mid, in_dwell, 2 * window, config)
    for j, (s, e) in enumerate(candidates):
        duration = (t_ns[e - 1] - t_ns[s]) / 1e9 + 2 * window * dt_ns / 1e9
        f_guess = float(np.nanmedian(mid[motion.at(s, e)])) / (2 * np.pi)
        if duration < config.min_rotation_s or f_guess * duration < config.min_turns:
            continue
        before = dwells[:, 1][dwells[:, 1] <= s]
        after = dwells[:, 0][dwells[:, 0] >= e]
        low = max(before.max() if before.size else 0, candidates[j - 1, 1] if j else 0, s - 2 * window)
        high = min(after.min() if after.size else n, candidates[j + 1, 0] if j + 1 < len(candidates) else n, e + 2 * window)
        # the fits grow from the candidate's middle half: its ends can be the last seconds of a ramp
        # whose rate is within the steady tolerance of the rotation's (at 2 Hz a 10 deg/s^2 ramp's last
        # 7 s), and their phase, lagging quadratically, would spoil the fit and lose the rotation
        quarter = (e - s) // 4
        core_start, core_stop = s + quarter, e - quarter
        start, stop, search = core_start, core_stop, True
        for _ in range(2):
            fit = fit_sine(t_ns[start:stop], y.rows(slice(start, stop)), f_guess, search)
            f_guess, search = fit.rate_hz, False
            start, stop = _extend(core_start, core_stop, low, high,
                                  lambda i, f=fit: ((y.rows(i) - f.model(t_ns[i])) ** 2 / f.sigma**2).mean(axis=1),
                                  config.cusum_kappa)
        fit = fit_sine(t_ns[start:stop], y.rows(slice(start, stop)), f_guess, False)
        chi2 = float(np.mean(fit.sigma**2 / var))
        if chi2 > config.max_residual_ratio**2:
            continue
        name, off = axis_from_normal(np.cross(fit.coef[:, 1], fit.coef[:, 2]))
        rotations.append(Rotation(int(start), int(stop), fit, name, off, chi2))
    moving = np.ones(n, bool)
    for r in rotations:
        moving[r.start : r.stop] = False
    # a time gap (as the stillness detector has it) between one dwell's last sample and the next one's first
    gap = steps_over(t_ns, config.stillness.gap_factor * dt_ns)
    recorded = np.array([not gap[e - 1 : s].any() for e, s in zip(dwells[:-1, 1], dwells[1:, 0])], bool)
    sequences, hand = _sequences(y, dwells, means, offset, moving, recorded, config)
    return BlindSegmentation(tuple(rotations), dwells, sequences, noise_sd, offset, hand, short)


def noise_sd_of(y: np.ndarray | Outputs, dwells: np.ndarray) -> np.ndarray:
    """Noise standard deviation per channel: pooled within the dwells, or,
    without dwells, from second differences (6 sigma^2 for white noise)."""
    y = Outputs.of(y)
    if len(dwells):
        squares = np.zeros(y.width)
        for s, e in dwells:
            for r, whole in enumerate(y.columns):  # a column at a time: a dwell of millions of samples makes no n x 3 temporaries
                column = whole[s:e] - whole[s:e].mean()
                squares[r] += column @ column
        dof = max(int((dwells[:, 1] - dwells[:, 0]).sum()) - len(dwells), 1)
        sd = np.sqrt(squares / dof)
    else:
        second = np.diff(y.rows(slice(None)), 2, axis=0)
        sd = 1.4826 * np.median(np.abs(second - np.median(second, axis=0)), axis=0) / np.sqrt(6.0)
    return np.maximum(sd, np.sqrt(1.0 / 12.0) if y.integer() else 1e-12)
