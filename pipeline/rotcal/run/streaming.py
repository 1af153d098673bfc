"""Segments and segment fits of a labelled capture read block by block, in
memory bounded by the block, not by the capture.

The segments are the label runs of ``segment.segment_by_labels`` (a run
is consecutive samples of one table axis and rate; a run starts where
either changes, so it may cross any block boundary), and each segment's
three-parameter fit against the table angle (``fit.segments``) is linear in
(1, sin theta, cos theta): its normal equations are sums over the samples,
additive across blocks (``fit.normal.NormalSums``). A first pass finds the
runs and accumulates those sums with what the fit's refusals need (sample
count, distinct static angles, the arc covered, each channel's range); a
second pass, at the solved coefficients, accumulates the residual
statistics (``fit.normal.ResidualSums``). Both give the in-memory tables to
rounding, whatever the block boundaries.

Blocks are frames of the canonical sample columns (t_ns, u, v, w, axis,
rate_hz, angle_deg) of one capture in time order; ``blocks()`` yields them
anew for each pass.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np
import polars as pl

from rotcal.config import FitConfig
from rotcal.fit.normal import NormalSums, ResidualSums, coefficient_covariance
from rotcal.fit.segments import SegmentFit, angle_step, arc_bounds, arc_from, finite, refusal_from, sine3_result, stuck_from, widened
from rotcal.fit.sines import BLOCK_SAMPLES, sincos_deg
from rotcal.fit.wander import offset_floor
from rotcal.metrology.simultaneous import SegmentSums
from rotcal.model.physics import AXES, CHANNELS
from rotcal.segment.labelled import segments_frame

Blocks = Callable[[], Iterator[pl.DataFrame]]


@dataclass(eq=False)
class _Run:
    """One segment's labels, span and sums, as far as the blocks have gone."""

    segment: int
    axis: int
    rate_hz: float
    first: int  # the sample number (from the capture's start) of its first sample
    t_start_ns: int
    t_end_ns: int = 0
    n: int = 0
    angle_runs: int = 0
    has_angle: bool = True
    normal: NormalSums = field(default_factory=NormalSums)
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
            return  # never fitted (angle_source "none"): no sums needed
        for a in range(0, angle.size, BLOCK_SAMPLES):  # pieces that stay in the core's cache, as sine3_fit's
            self.normal.add(*sincos_deg(angle[a : a + BLOCK_SAMPLES]), [y[a : a + BLOCK_SAMPLES] for y in channels])
        self.low = np.minimum(self.low, [y.min() for y in channels])
        self.high = np.maximum(self.high, [y.max() for y in channels])
        low, high = arc_bounds(angle)
        self.arc_low, self.arc_high = np.minimum(self.arc_low, low), np.maximum(self.arc_high, high)
        if self.kind == "static":
            self.angles.update(np.unique(angle).tolist())


def _columns(block: pl.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """t_ns, axis code (-1 null), rate and angle (NaN null), channels of a block."""
    axis = block["axis"].cast(pl.Enum(AXES)).to_physical().cast(pl.Int64).fill_null(-1).to_numpy()
    rate, angle = (block[c].cast(pl.Float64).fill_null(np.nan).to_numpy() for c in ("rate_hz", "angle_deg"))
    return block["t_ns"].to_numpy(), axis, rate, angle, [block[c].cast(pl.Float64).to_numpy() for c in CHANNELS]


def _differs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a != b, NaN equal to NaN (polars' ``ne_missing`` on nulls)."""
    return (a != b) & ~(np.isnan(a) & np.isnan(b))


def label_runs(blocks: Blocks) -> tuple[list[_Run], int]:
    """The first pass: every labelled run (segment) with its sums, and the number of samples."""
    runs: list[_Run] = []
    last = (np.int64(-2), np.nan, np.nan)  # the previous sample's axis, rate, angle (none before the first)
    offset = 0
    for block in blocks():
        if block.height == 0:
            continue
        t_ns, axis, rate, angle, channels = _columns(block)
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
    return runs, offset


def residual_pass(blocks: Blocks, runs: list[_Run], coefs: dict[int, np.ndarray],
                  rows: np.ndarray) -> tuple[dict[int, ResidualSums], pl.DataFrame]:
    """The second pass: each fitted segment's residual statistics at its
    coefficients, and the samples at the sorted sample numbers ``rows``
    gathered whole (with their ``segment`` and sample number ``row``)."""
    sums = {k: ResidualSums(c) for k, c in coefs.items()}
    fitted = [r for r in runs if r.segment in sums]
    starts = np.array([r.first for r in fitted], np.int64)
    gathered, offset = [], 0
    for block in blocks():
        m = block.height
        lo, hi = np.searchsorted(starts + [r.n for r in fitted], offset, "right"), np.searchsorted(starts, offset + m)
        if lo < hi:
            _, _, _, angle, channels = _columns(block)
            for run in fitted[lo:hi]:
                a, b = max(run.first - offset, 0), min(run.first + run.n - offset, m)
                for p in range(a, b, BLOCK_SAMPLES):
                    q = min(p + BLOCK_SAMPLES, b)
                    sums[run.segment].add(*sincos_deg(angle[p:q]), [y[p:q] for y in channels])
        wanted = rows[np.searchsorted(rows, offset) : np.searchsorted(rows, offset + m)]
        if wanted.size:
            gathered.append(block[wanted - offset].with_columns(row=pl.Series(wanted)))
        offset += m
    return sums, pl.concat(gathered)


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
        return with_segments(residual_pass(self.blocks, [], {}, np.unique(rows))[1], self.sizes).drop("row")


def stream_segments(blocks: Blocks, dataset: str, angle_source: str, config: FitConfig, max_samples: int) -> StreamedSegments:
    """The segments and three-parameter fits of the static and rotation
    segments with an angle reference (two passes over ``blocks``), with the
    samples the later stages read gathered in the second (``StreamedSegments``)."""
    runs, n_samples = label_runs(blocks)
    reasons, coefs = {}, {}
    for r in (r for r in runs if r.has_angle):
        reasons[r.segment] = (refusal_from(r.kind, angle_source, r.n, len(r.angles), arc_from(r.arc_low, r.arc_high), config)
                              or stuck_from(r.low, r.high))
        if reasons[r.segment] is None:
            coefs[r.segment], _ = r.normal.solve()
    fitted = [r for r in runs if r.segment in coefs]
    static = [np.arange(r.first, r.first + r.n) for r in runs if r.kind == "static"]
    from rotcal.diagnose.observed import thinned_rows  # the rows the diagnosis will model, asked of it

    thinned = thinned_rows(np.array([r.first for r in fitted], np.int64), np.array([r.n for r in fitted], np.int64), max_samples)
    residuals, gathered = residual_pass(blocks, runs, coefs, np.unique(np.concatenate([[0], thinned, *static])))
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
    fits, sums = [], {}
    for r in (r for r in runs if r.has_angle):
        if (reason := reasons[r.segment]) is not None:
            fits.append(SegmentFit.failed(r.segment, r.n, reason, r.rate_hz))
            continue
        coef, xtx_inv = r.normal.solve()
        res = residuals[r.segment]
        rtr = res.products()
        fit = finite(sine3_result(r.segment, r.rate_hz, r.n, coef, coefficient_covariance(rtr, xtx_inv, r.n), rtr,
                                  res.max_abs, res.lag, res.lag2), r.rate_hz)
        fits.append(widened(fit, angle_step(r.rate_hz, r.t_start_ns, r.t_end_ns, r.n)))
        sums[r.segment] = SegmentSums(r.segment, AXES[r.axis], r.n, r.normal.gram, r.normal.xty.T.copy(), coef, rtr,
                                      float(np.max(np.abs(np.r_[r.low, r.high]))))
    angled = [r for r in runs if r.has_angle]  # the offsets' wander between segments, as in memory (``fit.wander``)
    fits = offset_floor(fits, np.array([(r.t_start_ns / 1e9 + r.t_end_ns / 1e9) / 2 for r in angled]),
                        np.array([r.t_end_ns / 1e9 - r.t_start_ns / 1e9 for r in angled]), [(r.kind, r.rate_hz) for r in angled])
    sizes = {r.segment: (r.first, r.n) for r in runs}
    return StreamedSegments(blocks, segments, fits, sums, with_segments(gathered, sizes), frozenset(r.segment for r in fitted),
                            sizes, n_samples)
