"""The DUT's motion between its dwells: the angular rate and axis of its
roughly calibrated output direction (``angular_rate``), computed block by
block over the samples out of every dwell (``Motion``), where blind
segmentation (``rotcal.segment.blind``) looks for rotations."""

from __future__ import annotations

import numpy as np

from rotcal.model.columns import Outputs


def angular_rate(t_ns: np.ndarray, direction: np.ndarray, window: int, max_step_ns: float,
                 typical_dt_ns: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Angular rate (rad/s) and axis of ``direction`` (rows, roughly
    offset-free outputs) in the ``window`` sample pairs before and after
    every sample (rows: before, after; NaN where a window is empty). Pairs
    across a gap are left out.

    The axis is the direction of the summed cross products of consecutive
    unit vectors; the rate sums the turns of consecutive directions
    projected on the plane normal to the local axis, so that an offset left
    along the axis (a rough calibration from one axis's data cannot see it)
    does not bias it. ``typical_dt_ns``: the capture's median sample
    period, where ``t_ns`` is a block of it (else this block's).
    """
    unit = direction / np.linalg.norm(direction, axis=1)[:, None]
    dt = np.diff(t_ns).astype(float)
    valid = dt <= max_step_ns
    n = unit.shape[0]
    cross = np.where(valid[:, None], np.cross(unit[:-1], unit[1:]), 0.0)
    csum = np.vstack([np.zeros(3), np.cumsum(cross, axis=0)])
    pair = np.arange(n - 1)
    local = csum[np.clip(pair + window + 1, 0, n - 1)] - csum[np.clip(pair - window, 0, n - 1)]
    local /= np.maximum(np.linalg.norm(local, axis=1), 1e-300)[:, None]
    p0 = unit[:-1] - np.einsum("ij,ij->i", unit[:-1], local)[:, None] * local
    p1 = unit[1:] - np.einsum("ij,ij->i", unit[1:], local)[:, None] * local
    turn = np.arctan2(np.einsum("ij,ij->i", np.cross(p0, p1), local), np.einsum("ij,ij->i", p0, p1))
    turn = np.where(valid, turn, 0.0)
    # a turn is counted positive about the local axis, which the window's own sum defines
    asum = np.r_[0.0, np.cumsum(np.abs(turn) * np.sign(np.einsum("ij,ij->i", cross, local)))]
    tsum = np.r_[0.0, np.cumsum(np.where(valid, dt, 0.0))] / 1e9
    idx = np.arange(n)
    lo, hi = np.clip(idx - window, 0, n - 1), np.clip(idx + window, 0, n - 1)
    vec = np.stack([csum[idx] - csum[lo], csum[hi] - csum[idx]])
    angle = np.abs(np.stack([asum[idx] - asum[lo], asum[hi] - asum[idx]]))
    span = np.stack([tsum[idx] - tsum[lo], tsum[hi] - tsum[idx]])
    full = span > 0.5 * window * (np.median(dt) if typical_dt_ns is None else typical_dt_ns) / 1e9
    rate = np.where(full, angle / np.where(span > 0, span, 1.0), np.nan)
    norm = np.linalg.norm(vec, axis=2)
    axis = vec / np.where(norm > 0, norm, 1.0)[..., None]
    return rate, axis


# samples of a block of ``angular_rate``: its arrays (a dozen n x 3) stay a few tens of MB
MOTION_BLOCK = 1 << 18


class Motion:
    """``angular_rate`` where the samples are out of every dwell (the only
    place a rotation is looked for), block by block: each block padded by
    the rate's reach (two windows and a pair) so its samples get the
    values the whole capture's would. ``pos`` the samples (out of the
    dwells), ``rate`` (2, len(pos)) before and after, ``alignment`` the
    cosine between the axes before and after; ``axis(i)`` recomputed where
    asked (a few samples)."""

    def __init__(self, t_ns: np.ndarray, y: Outputs, offset: np.ndarray, to_unit: np.ndarray, in_dwell: np.ndarray,
                 window: int, dt_ns: float) -> None:
        self._args = (t_ns, y, offset, to_unit, window, dt_ns)
        self.pos = np.flatnonzero(~in_dwell)
        self.rate, self.alignment = np.empty((2, self.pos.size)), np.empty(self.pos.size)
        k = 0
        for s, e in runs_of(~in_dwell):
            for a in range(s, e, MOTION_BLOCK):
                b = min(a + MOTION_BLOCK, e)
                rate, axis = self._block(a, b)
                self.rate[:, k : k + b - a], self.alignment[k : k + b - a] = rate, np.einsum("ij,ij->i", axis[0], axis[1])
                k += b - a

    def _block(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        t_ns, y, offset, to_unit, window, dt_ns = self._args
        reach = 2 * window + 4
        lo, hi = max(0, a - reach), min(t_ns.size, b + reach)
        rate, axis = angular_rate(t_ns[lo:hi], (y.rows(slice(lo, hi)) - offset) @ to_unit.T, window, 1.5 * dt_ns, dt_ns)
        return rate[:, a - lo : b - lo], axis[:, a - lo : b - lo]

    def at(self, start: int, stop: int) -> slice:
        """The compact positions of samples ``start:stop`` (all out of the dwells)."""
        first = int(np.searchsorted(self.pos, start))
        return slice(first, first + stop - start)

    def axis(self, i: int) -> np.ndarray:
        """(2, 3) the axes before and after sample ``i``."""
        return self._block(i, i + 1)[1][:, 0]


def runs_of(mask: np.ndarray) -> np.ndarray:
    """Rows ``start, stop`` of the runs of True in ``mask``."""
    edges = np.diff(np.r_[0, mask.astype(np.int8), 0])
    return np.column_stack([np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)])
