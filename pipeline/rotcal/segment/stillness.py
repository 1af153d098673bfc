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

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.model.columns import Outputs, sample_step, steps_over
from rotcal.model.physics import CHANNELS

NOISY_FACTOR = 10.0  # a noisy rest: windows up to this many times the threshold's variance (about 3.2 x its std)
NOISE_FRACTION = 0.01  # a rest's noise sd below this fraction of the output's range (MEMS: about 0.1 %)
PLATEAU = 1.5  # second differences that grow less than this from lag L to 2 L show the noise's variance at L
TREND_SIGMAS = 4.0  # a move: its first and last thirds' means differ by more than this many standard errors


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


def column_variance(y: np.ndarray, window: int, centre: float | None = None) -> np.ndarray:
    """Variance of every full window of ``window`` samples of one column:
    cumulative sums on median-centred data (O(n), no loop over samples),
    block by block (each block's windows from its own sums, which also
    keeps their rounding to a block's length). ``centre``: the column's
    median, where the caller has it."""
    out = np.empty(max(y.size - window + 1, 0))
    for a, block in _variance_blocks(y, window, _median(y) if centre is None else centre):
        out[a : a + block.size] = block
    return out


def _median(y: np.ndarray) -> float:
    return float(np.median(y)) if y.size else 0.0


def _variance_blocks(y: np.ndarray, window: int, centre: float) -> Iterator[tuple[int, np.ndarray]]:
    """``column_variance``'s blocks: (first window, the block's window variances)."""
    count = max(y.size - window + 1, 0)
    for a in range(0, count, VARIANCE_BLOCK):
        b = min(a + VARIANCE_BLOCK, count)
        centred = y[a : b + window - 1] - centre
        s1 = np.r_[0.0, np.cumsum(centred)]
        s2 = np.r_[0.0, np.cumsum(centred * centred)]
        mean = (s1[window:] - s1[:-window]) / window
        yield a, np.maximum((s2[window:] - s2[:-window]) / window - mean * mean, 0.0)


def window_ratios(t_ns: np.ndarray, y: np.ndarray | Outputs, config: StillnessConfig = StillnessConfig(),
                  dt_ns: float | None = None) -> tuple[np.ndarray, int]:
    """Every window's (by first sample, ``n - window + 1`` of them) largest
    variance ratio to its channel's noise floor (inf across a time gap),
    and the window length. ``dt_ns``: the median sample period, where the
    caller has it."""
    n = t_ns.size
    dt_s = (sample_step(t_ns) if dt_ns is None else dt_ns) / 1e9 if n > 1 else 1.0
    window = max(3, int(round(config.window_s / dt_s)))
    if n < window:
        return np.zeros(0), window
    outputs = Outputs.of(y)
    integer = outputs.integer()
    # each channel's floor first, then the ratios block by block: at most one column-long array at a time
    floors, centres = [], []
    # the output's range where gravity turns (its largest over the channels), from at most a million samples
    scale = max(float(np.ptp(np.percentile(c[:: max(1, n // 1_000_000)], [1.0, 99.0]))) for c in outputs.columns)
    for column in outputs.columns:
        second = np.diff(column, 2)
        second -= np.median(second, overwrite_input=True)  # (the median of the values, whatever their order)
        white = (1.4826 * np.median(np.abs(second, out=second), overwrite_input=True)) ** 2 / 6.0
        del second
        factor = filter_memory_factor(column, window, config.floor_percentile)
        # a filter's memory only where the noise it gives stays far below that range (a rotation's signal does not)
        white *= factor if factor * white < (NOISE_FRACTION * scale) ** 2 else 1.0
        centres.append(_median(column))
        var = column_variance(column, window, centres[-1])
        floors.append(max(min(float(np.percentile(var, config.floor_percentile, overwrite_input=True)), white),
                          1.0 / 12.0 if integer else 1e-12))
        del var
    ratio = np.zeros(n - window + 1)
    for column, centre, floor in zip(outputs.columns, centres, floors):
        for a, var in _variance_blocks(column, window, centre):
            var /= floor
            np.maximum(ratio[a : a + var.size], var, out=ratio[a : a + var.size])
    gap = steps_over(t_ns, config.gap_factor * dt_s * 1e9)
    if gap.any():  # a gap inside the window
        gap_before = np.zeros(n, np.int64)
        np.cumsum(gap, dtype=np.int64, out=gap_before[1:])
        ratio[gap_before[window - 1 :] != gap_before[: n - window + 1]] = np.inf
    return ratio, window


def _second_difference_floor(column: np.ndarray, lag: int, window: int, percentile: float) -> float:
    """The ``percentile`` of the window variances of y[k + 2L] - 2 y[k + L] + y[k]
    (the rests' quietest windows: moves are most of no recording's windows)."""
    second = column[2 * lag :] - 2 * column[lag : column.size - lag] + column[: column.size - 2 * lag]
    return float(np.percentile(column_variance(second, window), percentile, overwrite_input=True))


def filter_memory_factor(column: np.ndarray, window: int, percentile: float) -> float:
    """How much more the noise's variance is than white noise's second
    differences show: 1 for white noise; for a sensor whose low-pass filter
    correlates neighbouring samples, second differences at lags L = 1, 2,
    4, ... grow until L passes the filter's memory, and the factor is their
    growth to the first lag whose doubling adds less than ``PLATEAU`` (var
    = 6 sigma^2 wherever the noise is uncorrelated over L; a rotation's
    signal keeps growing as L^4, so no plateau leaves the factor 1). A
    low-pass at 0.1 of the sample rate reads 1/30 of its variance at L = 1:
    every rest then looked ten times too noisy to be one."""
    lags = [lag for lag in (1, 2, 4, 8, 16, 32) if column.size >= 2 * lag + window]
    values: list[float] = []
    for lag in lags:
        values.append(_second_difference_floor(column, lag, window, percentile))
        if len(values) > 1 and values[-1] < PLATEAU * values[-2]:
            return max(values[-2] / values[0], 1.0) if values[0] > 0 else 1.0
    return 1.0


def quiet_windows(t_ns: np.ndarray, y: np.ndarray | Outputs, config: StillnessConfig = StillnessConfig()
                  ) -> tuple[np.ndarray, int]:
    """Which windows (by first sample, ``n - window + 1`` of them) are quiet, and the window length."""
    ratio, window = window_ratios(t_ns, y, config)
    return ratio < config.threshold, window


def _covered(quiet: np.ndarray, window: int, n: int) -> np.ndarray:
    """True for every sample inside a quiet window: each run of quiet
    windows covers its first window's first sample to its last one's last
    (those spans merged where they meet, so that the marks do not add up)."""
    edges = np.flatnonzero(np.diff(quiet, prepend=False, append=False))
    first, end = edges[0::2], np.minimum(edges[1::2] + window - 1, n)
    if not first.size:
        return np.zeros(n, bool)
    apart = first[1:] > end[:-1]
    cover = np.zeros(n + 1, np.int8)
    cover[first[np.r_[True, apart]]] = 1
    cover[end[np.r_[apart, True]]] = -1
    return np.cumsum(cover[:-1], dtype=np.int8) > 0


def _jumps(quiet: np.ndarray, window: int, n: int) -> np.ndarray:
    """Where no quiet window (first sample in ``i - window + 1 .. i - 1``)
    holds both samples ``i - 1`` and ``i``: the count of quiet windows
    starting before ``i`` less that before ``i - window + 1``, a block of
    samples at a time."""
    starts_before = np.zeros(quiet.size + 1, np.int64 if quiet.size >= 2**31 else np.int32)
    np.cumsum(quiet, dtype=starts_before.dtype, out=starts_before[1:])
    none = np.empty(n, bool)
    for a in range(0, n, VARIANCE_BLOCK):
        i = np.arange(a, min(a + VARIANCE_BLOCK, n))
        none[a : a + i.size] = (starts_before[np.clip(i, 0, quiet.size)]
                                == starts_before[np.clip(i - window + 1, 0, quiet.size)])
    return none


def still_intervals(t_ns: np.ndarray, y: np.ndarray | Outputs, config: StillnessConfig = StillnessConfig()) -> pl.DataFrame:
    """Still intervals at least ``min_dwell_s`` long: sample range, times,
    per-channel mean and standard deviation."""
    return still_and_short(t_ns, y, config)[0]


def still_and_short(t_ns: np.ndarray, y: np.ndarray | Outputs, config: StillnessConfig = StillnessConfig(),
                    dt_ns: float | None = None) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The still intervals (``still_intervals``) and the detector's
    rejections, each with its ``reason``: runs of still samples shorter
    than ``min_dwell_s`` (cut by a time gap or a jump), and *noisy rests*,
    at least ``min_dwell_s`` of windows whose variance exceeds the
    threshold but stays within ``NOISY_FACTOR`` times it with no trend in
    the mean (a DUT held by hand, or shaken: no move between two poses, yet
    noisier than the recording's rests). ``dt_ns``: the median sample
    period, where the caller has it."""
    outputs = Outputs.of(y)
    if dt_ns is None:
        dt_ns = sample_step(t_ns) if t_ns.size > 1 else 1e9
    ratio, window = window_ratios(t_ns, outputs, config, dt_ns)
    quiet = ratio < config.threshold
    mask = _covered(quiet, window, t_ns.size)
    gap = np.r_[False, steps_over(t_ns, config.gap_factor * dt_ns)]  # gap[i]: between samples i-1 and i
    # a jump between samples i-1 and i: no quiet window holds both
    gap[1:] |= mask[:-1] & mask[1:] & _jumps(quiet, window, t_ns.size)[1:]
    del quiet
    starts, ends = _runs(mask, gap)
    long = (t_ns[ends - 1] - t_ns[starts]) / 1e9 + dt_ns / 1e9 >= config.min_dwell_s
    short = _interval_frame(t_ns, outputs, starts[~long], ends[~long]).with_columns(reason=pl.lit(short_reason(config)))
    return _interval_frame(t_ns, outputs, starts[long], ends[long]), pl.concat([short, _noisy_rests(
        t_ns, outputs, ratio, window, mask, gap, config, dt_ns)]).sort("t_start_ns")


def _runs(mask: np.ndarray, gap: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and end (exclusive) samples of the runs of ``mask``, split at ``gap``."""
    starts = np.flatnonzero(mask & (np.r_[True, ~mask[:-1]] | gap))
    ends = np.flatnonzero(mask & (np.r_[~mask[1:], True] | np.r_[gap[1:], True])) + 1
    return starts, ends


def _noisy_rests(t_ns: np.ndarray, y: Outputs, ratio: np.ndarray, window: int, still: np.ndarray,
                 gap: np.ndarray, config: StillnessConfig, dt_ns: float) -> pl.DataFrame:
    """The noisy rests (``still_and_short``) outside the still samples
    ``still``, with their reason: the scatter, relative to the noise floor,
    of their quietest half of windows."""
    loose = _covered(ratio < config.threshold * NOISY_FACTOR, window, t_ns.size) & ~still
    starts, ends = _runs(loose, gap)
    kept: list[tuple[int, int]] = []
    scatter: list[float] = []
    for a, b in zip(starts.tolist(), ends.tolist()):
        third = (b - a) // 3
        # two windows at least: a rest's edge (windows over the rest and the move's start) is not a rest
        if (t_ns[b - 1] - t_ns[a] + dt_ns) / 1e9 < max(config.min_dwell_s, 2 * config.window_s) or third < 2:
            continue
        # a move (a hand turning the DUT slowly) has a trend in its mean; a noisy rest does not
        first, last = y.rows(slice(a, a + third)), y.rows(slice(b - third, b))
        se = np.sqrt((first.var(axis=0, ddof=1) + last.var(axis=0, ddof=1)) / third)
        if np.all(np.abs(last.mean(axis=0) - first.mean(axis=0)) <= TREND_SIGMAS * np.maximum(se, 1e-300)):
            kept.append((a, b))
            scatter.append(float(np.sqrt(np.median(ratio[a : max(a + 1, b - window + 1)]))))
    bounds = np.array(kept, dtype=np.int64).reshape(-1, 2)
    limit = float(np.sqrt(config.threshold))
    return _interval_frame(t_ns, y, bounds[:, 0], bounds[:, 1]).with_columns(reason=pl.Series([
        f"too noisy for a rest: its samples scatter {x:.2g} times the recording's noise floor (a rest's may reach "
        f"{limit:.2g} times); held by hand, or vibration? not a move (no trend in its mean), so it is listed, not used"
        for x in scatter], dtype=pl.String))


def _interval_frame(t_ns: np.ndarray, y: Outputs, starts: np.ndarray, ends: np.ndarray) -> pl.DataFrame:
    rows = {"start": starts, "stop": ends, "t_start_ns": t_ns[starts], "t_end_ns": t_ns[ends - 1],
            "n_samples": ends - starts}
    for c, column in zip(CHANNELS, y.columns):
        rows[f"mean_{c}"] = np.array([column[a:b].mean() for a, b in zip(starts, ends)], dtype=float)
        rows[f"std_{c}"] = np.array([column[a:b].std(ddof=1) if b - a > 1 else np.nan for a, b in zip(starts, ends)],
                                    dtype=float)
    return pl.DataFrame(rows)


def unused_rows(dataset: str, capture: pl.Series | str, intervals: pl.DataFrame, interval_s: float) -> pl.DataFrame:
    """Still intervals (rows of ``still_and_short``'s columns, with their
    ``reason``) as rows of the ``still_unused`` table: each with its capture
    and why no result uses it."""
    from rotcal.tables import conform  # here: the detector itself needs no table contracts

    return conform(intervals.select(
        pl.lit(dataset).alias("dataset"), pl.lit(capture).alias("capture") if isinstance(capture, str) else capture.alias("capture"),
        "t_start_ns", "t_end_ns", rest_s=(pl.col("t_end_ns") - pl.col("t_start_ns")).cast(pl.Float64) / 1e9 + interval_s,
        n_samples=pl.col("n_samples").cast(pl.Int64), mean_u="mean_u", mean_v="mean_v", mean_w="mean_w",
        reason="reason"), "still_unused")


def short_reason(config: StillnessConfig) -> str:
    """Why the detector rejects a still run shorter than ``min_dwell_s``."""
    return (f"shorter than the stillness detector's minimum rest of {config.min_dwell_s:g} s (a time gap or a jump cut "
            "it): too short a mean to enter a fit")
