"""Segments and segment fits of a labelled capture read block by block, in
memory bounded by the block and the longest segment, not by the capture.

The segments are the label runs of ``segment.segment_by_labels`` (a run
is consecutive samples of one table axis and rate; a run starts where
either changes, so it may cross any block boundary). A first pass finds
the runs with what the fit's refusals need (sample count, distinct static
angles, the arc covered, each channel's range); a second pass collects each
segment's angles and channels as the blocks go by and, once a segment is
whole, fits it as a run in memory fits it (``fit.segments.segment_fit``:
the fit, the rounding's repeats, the residuals' periodogram), then lets
it go; the fits are then widened across segments as in memory
(``fit.segments.across_segments``). The fits equal the in-memory run's bit
for bit, whatever the block boundaries: the same functions on the same
arrays. A segment is held whole while it is fitted (40 bytes a sample)
because its noise spectrum and its output step read all its samples.

Blocks are frames of the canonical sample columns (t_ns, u, v, w, axis,
rate_hz, angle_deg) of one capture in time order; ``blocks()`` yields them
anew for each pass.
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import polars as pl

from rotcal.config import FitConfig
from rotcal.fit.pooled import across_segments, record_noise_pooled
from rotcal.fit.refusals import arc_bounds, arc_from, refusal_from, stuck_from
from rotcal.fit.segments import SegmentFit, design, fitted_angle, segment_fit
from rotcal.metrology.simultaneous import SegmentSums
from rotcal.model.physics import AXES, CHANNELS
from rotcal.noise import FittedNoise
from rotcal.noise.allan import PooledAllan, octave_factors
from rotcal.noise.residuals import fit_residual_pieces, split_at_pauses
from rotcal.segment.labelled import segments_frame

Blocks = Callable[[], Iterator[pl.DataFrame]]


@dataclass(eq=False)
class _Run:
    """One segment's labels, span and what its refusals read, as far as the blocks have gone."""

    segment: int
    axis: int
    rate_hz: float
    first: int  # the sample number (from the capture's start) of its first sample
    t_start_ns: int
    t_end_ns: int = 0
    n: int = 0
    angle_runs: int = 0
    has_angle: bool = True
    low: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    high: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    arc_low: np.ndarray = field(default_factory=lambda: np.full(2, np.inf))
    arc_high: np.ndarray = field(default_factory=lambda: np.full(2, -np.inf))
    angles: set = field(default_factory=set)

    @property
    def kind(self) -> str:
        return "static" if self.rate_hz == 0 else "rotation"

    def add(self, t_ns: np.ndarray, angle: np.ndarray, channels: list[np.ndarray], angle_runs: int) -> None:
        self.t_end_ns = int(t_ns[-1])
        self.n += t_ns.size
        self.angle_runs += angle_runs
        self.has_angle &= not np.isnan(angle).any()
        if not self.has_angle:
            return  # never fitted (angle_source "none")
        self.low = np.minimum(self.low, [y.min() for y in channels])
        self.high = np.maximum(self.high, [y.max() for y in channels])
        low, high = arc_bounds(angle)
        self.arc_low, self.arc_high = np.minimum(self.arc_low, low), np.maximum(self.arc_high, high)
        if self.kind == "static":
            self.angles.update(np.unique(angle).tolist())

    def refusal(self, angle_source: str, config: FitConfig) -> str | None:
        """Why the fit refuses the segment (``fit.segments.refusal``, then a stuck channel), or None."""
        return (refusal_from(self.kind, angle_source, self.n, len(self.angles), arc_from(self.arc_low, self.arc_high), config)
                or stuck_from(self.low, self.high))


def _columns(block: pl.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """t_ns, axis code (-1 null), rate and angle (NaN null), channels of a block."""
    axis = block["axis"].cast(pl.Enum(AXES)).to_physical().cast(pl.Int64).fill_null(-1).to_numpy()
    rate, angle = (block[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in ("rate_hz", "angle_deg"))
    return block["t_ns"].to_numpy(), axis, rate, angle, [block[c].cast(pl.Float64).to_numpy() for c in CHANNELS]


def _differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a != b, NaN equal to NaN (polars' ``ne_missing`` on nulls)."""
    return (a != b) & ~(np.isnan(a) & np.isnan(b))


def label_runs(blocks: Blocks) -> tuple[list[_Run], int, float, float, tuple[float, float]]:
    """The first pass: every labelled run (segment) with what its refusals
    read, the number of samples, the sample interval (s) as
    ``noise.residuals.sample_interval_s`` reads it from every stamp (the
    median positive step) and as ``fit.segments.fit_segments`` reads it
    (the median step), both counted by value, so the pass holds only the
    distinct steps; and the first and last stamps (s)."""
    runs: list[_Run] = []
    last = (np.int64(-2), np.nan, np.nan)  # the previous sample's axis, rate, angle (none before the first)
    offset, last_t, first_t = 0, None, None
    steps: dict[int, int] = {}  # every step between successive stamps, counted by value
    for block in blocks():
        if block.height == 0:
            continue
        t_ns, axis, rate, angle, channels = _columns(block)
        step = np.diff(t_ns) if last_t is None else np.diff(t_ns, prepend=last_t)
        first_t = int(t_ns[0]) if first_t is None else first_t
        if step.size and step.min() == step.max():  # a logger's regular steps: one value, no sort
            steps[int(step[0])] = steps.get(int(step[0]), 0) + step.size
        else:
            for value, count in zip(*np.unique(step, return_counts=True)):
                steps[int(value)] = steps.get(int(value), 0) + int(count)
        last_t = t_ns[-1]
        start = np.r_[axis[0] != last[0], axis[1:] != axis[:-1]] | _differs(rate, np.r_[last[1], rate[:-1]])
        angle_change = _differs(angle, np.r_[last[2], angle[:-1]])
        labelled = (axis >= 0) & ~np.isnan(rate)
        cuts = np.r_[np.flatnonzero(start), axis.size]
        if cuts[0] != 0:  # the block continues the previous block's run
            cuts = np.r_[0, cuts]
        for a, b in zip(cuts[:-1], cuts[1:]):
            if not labelled[a]:
                continue
            if start[a]:
                runs.append(_Run(len(runs), int(axis[a]), float(rate[a]), offset + a, int(t_ns[a])))
            runs[-1].add(t_ns[a:b], angle[a:b], [y[a:b] for y in channels],
                         int(np.count_nonzero(angle_change[a + 1 : b])) + (1 if start[a] else int(angle_change[a])))
        last = (axis[-1], rate[-1], angle[-1])
        offset += axis.size
    positive = {v: k for v, k in steps.items() if v > 0}
    ends = (0.0, 0.0) if first_t is None or last_t is None else (float(first_t) / 1e9, float(last_t) / 1e9)
    return runs, offset, _median(positive) / 1e9, _median(steps) / 1e9, ends


def _median(counts: dict[int, int]) -> float:
    """The median of values given by their counts (the mean of the two middle ones of an even count); 0 with none."""
    if not counts:
        return 0.0
    values = np.array(sorted(counts), np.int64)
    cumulative = np.cumsum([counts[v] for v in values])
    n = int(cumulative[-1])
    low, high = (values[np.searchsorted(cumulative, k, "right")] for k in ((n - 1) // 2, n // 2))
    return float(low) if low == high else (float(low) + float(high)) / 2


def fit_pass(blocks: Blocks, runs: list[_Run], angle_source: str, config: FitConfig, rows: np.ndarray,
             noise: FittedNoise | None = None, record: FittedNoise | None = None) -> tuple[dict[int, SegmentFit], pl.DataFrame]:
    """The second pass: each run of ``runs`` fitted (``fit.segments.segment_fit``)
    once the blocks have given all its samples, its residual pieces pooled
    into ``noise`` (``noise.residuals``), and the samples at the sorted
    sample numbers ``rows`` gathered whole (with their ``segment`` and
    sample number ``row``)."""
    fits: dict[int, SegmentFit] = {}
    held: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}  # stamps, angles, channels: filled as the blocks come
    starts, ends = np.array([r.first for r in runs], np.int64), np.array([r.first + r.n for r in runs], np.int64)
    gathered, offset = [], 0
    for block in blocks():
        m = block.height
        lo, hi = np.searchsorted(ends, offset, "right"), np.searchsorted(starts, offset + m)
        if lo < hi:
            t_ns, _, _, angle, channels = _columns(block)
            for run in runs[lo:hi]:
                a, b = max(run.first - offset, 0), min(run.first + run.n - offset, m)
                # the channels column by column in one array, as ``select(CHANNELS).to_numpy()`` gives them in memory
                t, theta, y = held.setdefault(run.segment, (np.empty(run.n, np.int64), np.empty(run.n),
                                                            np.empty((run.n, 3), order="F")))
                into = slice(offset + a - run.first, offset + b - run.first)
                t[into], theta[into] = t_ns[a:b], angle[a:b]
                for r, values in enumerate(channels):
                    y[into, r] = values[a:b]
                if run.first + run.n <= offset + m:  # whole: fitted, then let go
                    del held[run.segment]
                    fit = segment_fit(run.segment, run.kind, run.rate_hz, angle_source, theta, tuple(y.T),
                                      run.t_start_ns, run.t_end_ns, config)
                    fits[run.segment] = fit
                    if record is not None and fit.status == "ok":  # the offsets' noise model's pieces (``fit_segments``)
                        resid = y - design(fitted_angle(fit, theta, run.rate_hz)) @ fit.coef.T
                        for piece in split_at_pauses(t, resid, record.dt_s):
                            record.pooled.add(piece)
                        del resid
                    if noise is not None and fit.status == "ok" and np.isfinite(fit.coef).all():
                        for piece in fit_residual_pieces(t, y, theta, np.ascontiguousarray(fit.coef), run.rate_hz,
                                                         fit.rate_fit_hz, noise.dt_s) or ():
                            noise.pooled.add(piece)
        wanted = rows[np.searchsorted(rows, offset) : np.searchsorted(rows, offset + m)]
        if wanted.size:
            gathered.append(block[wanted - offset].with_columns(row=pl.Series(wanted)))
        offset += m
    return fits, pl.concat(gathered)


def with_segments(frame: pl.DataFrame, sizes: dict[int, tuple[int, int]]) -> pl.DataFrame:
    """Gathered samples with the ``segment`` column of ``segment_by_labels``
    (null outside the label runs; segments numbered in time order)."""
    first, count = (np.array([sizes[s][i] for s in sorted(sizes)], np.int64).reshape(-1) for i in (0, 1))
    row = frame["row"].to_numpy()
    k = np.searchsorted(first, row, "right") - 1
    inside = (k >= 0) & (row < (first + count)[np.maximum(k, 0)]) if first.size else np.zeros(row.size, bool)
    return frame.with_columns(segment=pl.Series(np.ma.masked_array(k, ~inside), dtype=pl.Int32))


@dataclass(frozen=True, eq=False)
class StreamedSegments:
    """What the two passes give: the ``segments`` table and the segment fits
    (as ``segment_by_labels`` + ``fit_segments`` give them in memory), each
    fitted segment's sums (``metrology.simultaneous.SegmentSums``), and the
    samples gathered on the way: the capture's first, the static segments'
    whole, and the diagnosis's thinned rows of the fitted segments
    (``diagnose.observed.thinned_rows``; ``thinned`` names those segments, ``sizes`` gives
    every segment's sample count)."""

    blocks: Blocks
    segments: pl.DataFrame
    fits: list[SegmentFit]
    sums: dict[int, SegmentSums]
    gathered: pl.DataFrame
    thinned: frozenset[int]
    sizes: dict[int, tuple[int, int]]   # segment -> (first sample number, samples)
    n_samples: int
    noise: FittedNoise | None = None  # the fitted segments' residual pieces, pooled for the noise model

    def noise_pooled(self) -> FittedNoise:
        """A copy of the pooled residual pieces (the noise stage adds the poses' to it)."""
        if self.noise is None:
            return FittedNoise(0.0, PooledAllan(np.zeros(0), len(CHANNELS)))
        return FittedNoise(self.noise.dt_s, copy.deepcopy(self.noise.pooled))

    @property
    def unlabelled(self) -> int:
        """Samples outside every label run."""
        return self.n_samples - sum(n for _, n in self.sizes.values())

    def static_samples(self) -> pl.DataFrame:
        """The capture's first sample and the static segments' samples."""
        static = self.segments.filter(pl.col("kind") == "static")["segment"]
        return self.gathered.filter((pl.col("row") == 0) | pl.col("segment").is_in(static.implode())).drop("row")

    def count(self, segments: frozenset[int]) -> int:
        """The samples of ``segments``."""
        return sum(self.sizes[s][1] for s in segments)

    def diagnosed_samples(self, segments: frozenset[int], max_samples: int) -> pl.DataFrame:
        """The capture's first sample and the rows ``diagnose.observed.observations``
        thins ``segments`` to: those gathered in the second pass, or, when
        the diagnosed segments are not those fitted then, a third pass."""
        first, count = (np.array([self.sizes[s][i] for s in sorted(segments)], np.int64) for i in (0, 1))
        from rotcal.diagnose.observed import thinned_rows  # the diagnosis's modules load when diagnosing

        rows = np.r_[0, thinned_rows(first, count, max_samples)]
        if segments == self.thinned:
            return self.gathered.filter(pl.col("row").is_in(rows)).drop("row")
        return with_segments(fit_pass(self.blocks, [], "", FitConfig(), np.unique(rows))[1], self.sizes).drop("row")


def stream_segments(blocks: Blocks, dataset: str, angle_source: str, config: FitConfig, max_samples: int,
                    pool_noise: bool = True) -> StreamedSegments:
    """The segments and three-parameter fits of the static and rotation
    segments with an angle reference (two passes over ``blocks``), with the
    samples the later stages read gathered in the second, and (``pool_noise``)
    their residual pieces pooled for the noise model (``StreamedSegments``)."""
    runs, n_samples, dt_s, dt_record, ends = label_runs(blocks)
    angled = [r for r in runs if r.has_angle]
    reasons = {r.segment: r.refusal(angle_source, config) for r in angled}
    fitted = [r for r in angled if reasons[r.segment] is None]
    static = [np.arange(r.first, r.first + r.n) for r in runs if r.kind == "static"]
    from rotcal.diagnose.observed import thinned_rows  # the rows the diagnosis will model, asked of it

    thinned = thinned_rows(np.array([r.first for r in fitted], np.int64), np.array([r.n for r in fitted], np.int64), max_samples)
    noise = FittedNoise(dt_s, PooledAllan(octave_factors(n_samples), len(CHANNELS))) if dt_s > 0 and pool_noise else None
    record = FittedNoise(dt_record, PooledAllan(octave_factors(n_samples), len(CHANNELS))) if dt_record > 0 else None
    own, gathered = fit_pass(blocks, fitted, angle_source, config, np.unique(np.concatenate([[0], thinned, *static])), noise,
                             record)
    segments = segments_frame({
        "segment": pl.Series([r.segment for r in runs], dtype=pl.Int32),
        "capture": [gathered["capture"][0]] * len(runs),
        "kind": [r.kind for r in runs],
        "axis": pl.Series([AXES[r.axis] for r in runs], dtype=pl.Enum(AXES)),
        "rate_hz": pl.Series([r.rate_hz for r in runs], dtype=pl.Float64),
        "t_start_ns": pl.Series([r.t_start_ns for r in runs], dtype=pl.Int64),
        "t_end_ns": pl.Series([r.t_end_ns for r in runs], dtype=pl.Int64),
        "n_samples": pl.Series([r.n for r in runs], dtype=pl.Int64),
        "n_steps": pl.Series([r.angle_runs for r in runs], dtype=pl.Int64),
        "label_source": [gathered["label_source"].fill_null("file")[0]] * len(runs),
        "has_angle": pl.Series([r.has_angle for r in runs], dtype=pl.Boolean),
    }, dataset, angle_source)
    fits = [own[r.segment] if r.segment in own else SegmentFit.failed(r.segment, r.n, str(reasons[r.segment]), r.rate_hz)
            for r in angled]
    t_first, t_last = (np.array([t / 1e9 for t in ts], float) for ts in
                       ([r.t_start_ns for r in angled], [r.t_end_ns for r in angled]))
    fits = across_segments(fits, t_first, t_last, [(r.kind, r.rate_hz) for r in angled],
                           [AXES[r.axis] if r.axis >= 0 else None for r in angled],
                           lambda _: None if record is None else record_noise_pooled(record.pooled, dt_record, ends),
                           modelled=dt_record > 0, record_start_s=ends[0] if n_samples else None)
    axis = {r.segment: AXES[r.axis] for r in angled}
    sums = {f.segment: SegmentSums.of_fit(f.segment, axis[f.segment], f.n_samples, f.sums) for f in fits if f.sums is not None}
    sizes = {r.segment: (r.first, r.n) for r in runs}
    return StreamedSegments(blocks, segments, fits, sums, with_segments(gathered, sizes), frozenset(r.segment for r in fitted),
                            sizes, n_samples, noise)
