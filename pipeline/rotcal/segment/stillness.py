"""Segmentation by stillness: find the intervals in which the DUT rests.

A moving-variance detector (the one imu_tk and most multi-position methods
use), with its threshold set from the recording itself: the noise floor is
the 10th percentile of each channel's moving variance (hand-placed and table
sessions rest most of the time), and a window is still when no channel's
variance exceeds ``threshold`` times its floor. A recording that never
rests (a capture of one constant rotation) has no still windows to set that
percentile, so the floor is also capped by the white-noise variance that
second differences show (var(y[k+1] - 2 y[k] + y[k-1]) = 6 sigma^2, robustly
from their median absolute deviation; slow motion barely adds to it). Nothing
beyond the samples and their time stamps is needed.

A still interval is a chain of overlapping quiet windows: it ends where no
quiet window holds both of two neighbouring samples. That is where the
output jumped between them: a move faster than one sample (a table indexing
within a sample period), whose windows on either side are both quiet while
every window across it is not. A time gap of ``gap_factor`` periods ends an
interval too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS


@dataclass(frozen=True)
class StillnessConfig:
    window_s: float = 1.0
    threshold: float = 10.0   # variance ratio to the noise floor (about 3.2 x the noise std)
    min_dwell_s: float = 1.0
    floor_percentile: float = 10.0
    gap_factor: float = 5.0   # a time gap this many sample periods long ends an interval


# samples a window variance is summed over at a time: a block's cumulative sums stay a few MB
VARIANCE_BLOCK = 1 << 18


def moving_variance(y: np.ndarray, window: int) -> np.ndarray:
    """Variance of every full window of ``window`` samples, per column."""
    return np.column_stack([column_variance(y[:, r], window) for r in range(y.shape[1])])


def column_variance(y: np.ndarray, window: int) -> np.ndarray:
    """Variance of every full window of ``window`` samples of one column:
    cumulative sums on median-centred data (O(n), no loop over samples),
    block by block (each block's windows from its own sums, which also
    keeps their rounding to a block's length)."""
    count = max(y.size - window + 1, 0)
    out = np.empty(count)
    centre = float(np.median(y)) if y.size else 0.0
    for a in range(0, count, VARIANCE_BLOCK):
        b = min(a + VARIANCE_BLOCK, count)
        centred = y[a : b + window - 1] - centre
        s1 = np.r_[0.0, np.cumsum(centred)]
        s2 = np.r_[0.0, np.cumsum(centred * centred)]
        mean = (s1[window:] - s1[:-window]) / window
        out[a:b] = np.maximum((s2[window:] - s2[:-window]) / window - mean * mean, 0.0)
    return out


def quiet_windows(t_ns: np.ndarray, y: np.ndarray, config: StillnessConfig = StillnessConfig()) -> tuple[np.ndarray, int]:
    """Which windows (by first sample, ``n - window + 1`` of them) are quiet, and the window length."""
    n = t_ns.size
    dt_s = float(np.median(np.diff(t_ns))) / 1e9 if n > 1 else 1.0
    window = max(3, int(round(config.window_s / dt_s)))
    if n < window:
        return np.zeros(0, bool), window
    integer = all(np.all(y[:, r] == np.round(y[:, r])) for r in range(y.shape[1]))
    quiet = np.ones(n - window + 1, bool)
    for r in range(y.shape[1]):  # a column at a time: its temporaries, not the table's
        second = np.diff(y[:, r], 2)
        second -= np.median(second)
        white = (1.4826 * np.median(np.abs(second))) ** 2 / 6.0
        del second
        var = column_variance(y[:, r], window)
        floor = max(min(float(np.percentile(var, config.floor_percentile)), white), 1.0 / 12.0 if integer else 1e-12)
        quiet &= var / floor < config.threshold
    gap = np.diff(t_ns) > config.gap_factor * dt_s * 1e9
    gap_before = np.concatenate([[0], np.cumsum(gap)])
    quiet &= gap_before[window - 1 :] == gap_before[: n - window + 1]  # no gap inside the window
    return quiet, window


def _covered(quiet: np.ndarray, window: int, n: int) -> np.ndarray:
    """True for every sample inside a quiet window."""
    cover = np.zeros(n + 1, int)
    starts = np.flatnonzero(quiet)
    np.add.at(cover, starts, 1)
    np.add.at(cover, starts + window, -1)
    return np.cumsum(cover[:-1]) > 0


def still_intervals(t_ns: np.ndarray, y: np.ndarray, config: StillnessConfig = StillnessConfig()) -> pl.DataFrame:
    """Still intervals at least ``min_dwell_s`` long: sample range, times,
    per-channel mean and standard deviation."""
    quiet, window = quiet_windows(t_ns, y, config)
    mask = _covered(quiet, window, t_ns.size)
    dt_ns = float(np.median(np.diff(t_ns))) if t_ns.size > 1 else 1e9
    gap = np.r_[False, np.diff(t_ns) > config.gap_factor * dt_ns]  # gap[i]: between samples i-1 and i
    # a jump between samples i-1 and i: no quiet window (first sample in i-window+1 .. i-1) holds both
    starts_before = np.r_[0, np.cumsum(quiet)]
    i = np.arange(t_ns.size)
    spanning = (starts_before[np.clip(i, 0, quiet.size)] - starts_before[np.clip(i - window + 1, 0, quiet.size)])
    gap |= np.r_[False, mask[:-1] & mask[1:]] & (spanning == 0)
    # runs of still samples, split at time gaps and jumps
    starts = np.flatnonzero(mask & (np.r_[True, ~mask[:-1]] | gap))
    ends = np.flatnonzero(mask & (np.r_[~mask[1:], True] | np.r_[gap[1:], True])) + 1
    long = (t_ns[ends - 1] - t_ns[starts]) / 1e9 + dt_ns / 1e9 >= config.min_dwell_s
    starts, ends = starts[long], ends[long]
    rows = {"start": starts, "stop": ends, "t_start_ns": t_ns[starts], "t_end_ns": t_ns[ends - 1],
            "n_samples": ends - starts}
    for r, c in enumerate(CHANNELS):
        rows[f"mean_{c}"] = np.array([y[a:b, r].mean() for a, b in zip(starts, ends)])
        rows[f"std_{c}"] = np.array([y[a:b, r].std(ddof=1) for a, b in zip(starts, ends)])
    return pl.DataFrame(rows)
