"""A regular sampling grid fitted to a capture's time stamps, the arithmetic
under ``timebase.check``.

The samples sit on ``t_k = a_run + T k``: a period ``T`` common to the
capture and one offset ``a`` per logging run, fitted by least squares to the
stamps ``s`` with every sample's slot ``k`` from rounding. Sample-length
arrays are worked on a block of ``_BLOCK`` samples at a time, so the
temporaries stay small on recordings of hundreds of millions of samples.
"""

from __future__ import annotations

import numpy as np

_BLOCK = 1 << 20  # samples a block, where the arithmetic goes a block at a time


def kept(a: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """``a[keep]``, without a copy when every row is kept."""
    return a if keep.all() else a[keep]


def intervals(s: np.ndarray) -> np.ndarray:
    """Successive intervals of the stamps, as differences of their float values."""
    return np.subtract(s[1:], s[:-1], dtype=np.float64)


def _grid_fit(s: np.ndarray, k: np.ndarray, run: np.ndarray) -> tuple[float, np.ndarray]:
    """Least squares ``s = a_run + T k``: the common period and each run's offset."""
    n_runs = int(run.max()) + 1
    count = np.bincount(run, minlength=n_runs)
    k_mean = np.bincount(run, k, n_runs) / count
    s_mean = np.bincount(run, s, n_runs) / count
    dk = k_mean[run]
    np.subtract(k, dk, out=dk)
    den = float(dk @ dk)
    if den > 0:
        ds = s_mean[run]
        np.subtract(s, ds, out=ds)
        period = float(dk @ ds / den)
    else:
        period = float(np.median(intervals(s)))
    return period, s_mean - period * k_mean


def grid_residuals(s: np.ndarray, k: np.ndarray, run: np.ndarray, period: float, offset: np.ndarray) -> np.ndarray:
    """The stamps' residuals from the grid, ``s - a_run - T k``, a block at a time."""
    resid = np.empty(s.size)
    for a in range(0, s.size, _BLOCK):
        block = slice(a, a + _BLOCK)
        resid[block] = s[block] - offset[run[block]] - period * k[block]
    return resid


def median(x: np.ndarray) -> float:
    """``np.median`` of a finite array, the same value without its general
    machinery (a few dozen microseconds a call, several calls a capture);
    ``x`` is scratch (partitioned in place)."""
    half = x.size // 2
    if x.size % 2:
        x.partition(half)
        return float(x[half])
    x.partition((half - 1, half))
    return float((x[half - 1] + x[half]) / 2)


def _robust_sd(x: np.ndarray) -> float:
    """1.4826 times the median absolute deviation; ``x`` is scratch (reordered, overwritten)."""
    if not x.size:
        return 0.0
    centre = median(x)
    np.subtract(x, centre, out=x)
    np.abs(x, out=x)
    return float(1.4826 * median(x))


def white_jitter(s: np.ndarray, k: np.ndarray, run: np.ndarray, period: float, offset: np.ndarray) -> float:
    """The white part of the stamp noise: the robust sd of successive
    residual differences within runs, over sqrt(2); the differences are
    taken a block at a time (blocks overlap by one sample)."""
    within = run[1:] == run[:-1]
    steps, filled = np.empty(np.count_nonzero(within)), 0
    for a in range(0, within.size, _BLOCK):
        b = min(a + _BLOCK, within.size)
        step = kept(np.diff(grid_residuals(s[a : b + 1], k[a : b + 1], run[a : b + 1], period, offset)), within[a:b])
        steps[filled : filled + step.size] = step
        filled += step.size
    return _robust_sd(steps) / np.sqrt(2.0)


def lag1_within(resid: np.ndarray, within: np.ndarray) -> float:
    """Lag-1 autocorrelation of the residuals within runs (Pearson's r of
    successive pairs, as ``np.corrcoef``), from sums over blocks of pairs:
    no copy of the residuals. 0 for fewer than three pairs or no scatter."""
    n = np.count_nonzero(within)
    if n <= 2:
        return 0.0

    def pairs():
        for a in range(0, within.size, _BLOCK):
            w = within[a : a + _BLOCK]
            yield resid[a : a + w.size][w], resid[a + 1 : a + 1 + w.size][w]

    mean = np.zeros(2)
    for x, y in pairs():
        mean += x.sum() / n, y.sum() / n
    sums = np.zeros(3)  # centred xx, yy, xy
    for x, y in pairs():
        x, y = x - mean[0], y - mean[1]
        sums += x @ x, y @ y, x @ y
    if sums[0] <= 0 or sums[1] <= 0:
        return 0.0
    return float(np.clip(sums[2] / np.sqrt(sums[0] * sums[1]), -1.0, 1.0))


def place_collisions(slot: np.ndarray, run: np.ndarray) -> np.ndarray:
    """New slots for samples that share one. The group of m samples claiming
    slot k fills k .. k+m-1 when exactly those slots are free (the previous
    sample sits at k-1 and the next at k+m), or k-m+1 .. k when exactly
    those are; only then do the empty slots say where they belong. Otherwise
    the samples get -1 (cannot be placed). Only the groups are worked on:
    most samples have a slot of their own."""
    key = run.astype(np.int64) * (1 << 40) + slot
    shared = key[1:] == key[:-1]
    if not shared.any():
        return slot
    member = np.flatnonzero(np.r_[False, shared] | np.r_[shared, False])  # samples in groups of two or more
    start = np.r_[True, key[member[1:]] != key[member[1:] - 1]]
    group = np.cumsum(start) - 1
    first = member[start]
    size = np.diff(np.r_[np.flatnonzero(start), member.size])
    pos = member - first[group]
    prev_key = np.where(first > 0, key[np.maximum(first - 1, 0)], np.iinfo(np.int64).min)
    after = first + size
    next_key = np.where(after < key.size, key[np.minimum(after, key.size - 1)], np.iinfo(np.int64).max)
    up = (next_key == key[first] + size) & (prev_key == key[first] - 1)
    down = (prev_key == key[first] - size) & (next_key == key[first] + 1)
    placed = slot.copy()
    placed[member] = np.where(up[group], slot[member] + pos,
                              np.where(down[group], slot[member] - size[group] + 1 + pos, -1))
    return placed


def grid_slots(s: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, float]:
    """Every stamp's slot on the grid and its logging run: slots counted
    from the intervals, runs split at every gap and joined again where the
    next run's line continues this one's (lost packets: the phase holds);
    then every slot re-read from the fitted lines. Returns the slots, the
    runs, the period, each run's offset and the white jitter about them."""
    d = intervals(s)
    distinct = np.concatenate(([True], d > 0))
    # equal stamps share a slot (a repeated stamp); any advance is at least one slot
    steps = d / period
    del d
    np.rint(steps, out=steps)
    np.maximum(steps, 1.0, out=steps)
    steps[~distinct[1:]] = 0.0
    run = np.zeros(s.size, np.int32)  # int32: one of the few sample-length arrays alive throughout
    np.cumsum(steps >= 2, dtype=np.int32, out=run[1:])
    k = np.zeros(s.size)
    np.cumsum(steps, out=k[1:])
    del steps
    for _ in range(3):
        period, offset = _grid_fit(s, k, run)
        jitter = white_jitter(s, k, run, period, offset)
        u_offset = np.maximum(jitter, 1.0) / np.sqrt(np.maximum(np.bincount(run, distinct), 1.0))
        slip = (offset[1:] - offset[:-1]) / period
        whole = np.rint(slip)
        tolerance = np.minimum(4 * np.hypot(u_offset[1:], u_offset[:-1]) + 1e-4 * period, period / 2)
        hold = np.abs(slip - whole) * period < tolerance
        joined = bool(hold.any())  # no run joins the one before: runs and slots stand as they are
        if joined:
            k += np.concatenate(([0.0], np.cumsum(np.where(hold, whole, 0.0))))[run]
            run = np.concatenate(([0], np.cumsum(~hold))).astype(np.int32)[run]
            period, offset = _grid_fit(s, k, run)
        reread = np.empty(s.size)  # np.rint((s - offset[run]) / period), a block at a time
        for a in range(0, s.size, _BLOCK):
            block = slice(a, a + _BLOCK)
            reread[block] = np.rint((s[block] - offset[run[block]]) / period)
        # a fixed point (no run joined, no slot re-read): a further pass would repeat this one exactly,
        # so its fit and jitter are those of the slots returned
        if not joined and np.array_equal(reread, k):
            return k, run, period, offset, jitter
        k = reread
    period, offset = _grid_fit(s, k, run)
    return k, run, period, offset, white_jitter(s, k, run, period, offset)
