"""``check.check_capture`` for a capture whose stamps are read in blocks,
with no sample-length array (issue 16, item 1).

The grid ``t_k = a_run + T k`` (``timebase.grid``) is fitted as in memory,
from sums that are additive over blocks: every slot ``k`` and logging run
is a function of the stamp and of a few numbers per run, recomputed in
each pass (``_Slots``): at first from the running count of intervals
(rounded to the first period), then re-read from the fitted lines. The
per-run sums are accumulated in the in-memory order (``np.add.at`` over
the blocks in turn is ``np.bincount``'s loop), so the means are the
in-memory means bit for bit; the cross products come in another order
(to rounding). The medians (first period, the robust jitter) are exact:
a histogram of the values narrows each rank to one bin, whose values are
then gathered (``_ranked``), each step one pass over the stamps; up to
``HELD`` values (a memory bound, not the capture's), all are gathered and
partitioned in one pass.

Captures with repeated stamps (duplicates, collisions to place) or whose
slots would need a sort are left to the in-memory check (``None``).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from rotcal.timebase.check import Gaps, GridStats, TimebaseConfig, grid_findings
from rotcal.timebase.grid import grid_residuals, intervals
from rotcal.timebase.streamed import Repairer, Stamps, StreamedTimebase, replaced

GATHER = 1 << 18  # values gathered and sorted to pick a rank
HELD = 1 << 24  # values up to which ranks are picked among all of them held at once (8 bytes each, 128 MB at most)
BINS = 1 << 12  # bins of a histogram narrowing a rank
SPILL_BLOCK = 1 << 18  # values read back from a temporary file at a time


class _NotStreamed(Exception):
    """The capture needs the in-memory check."""


def _ranked(values: Callable[[], Iterator[np.ndarray]], n: int, ranks: list[int]) -> list[float]:
    """The values of ``ranks`` (0-based, in ascending order of value) among
    the ``n`` values ``values()`` yields, exactly, a few passes each.

    Each rank's candidates lie in a range of values [lo, hi) (hi included
    while it is the maximum), with ``below`` values under it; a histogram
    of the range finds the bin holding the rank, until the range holds few
    enough values to sort or a single value. Up to ``HELD`` values, the
    ranks are picked among them all, in one pass and a partition (the
    memory stays bounded by ``HELD``, the time is a tenth)."""
    if n <= HELD:
        held, filled = np.empty(n), 0
        for x in values():
            held[filled : filled + x.size] = x
            filled += x.size
        held.partition(ranks)
        return [float(held[r]) for r in ranks]
    low, high = np.inf, -np.inf
    for x in values():
        if x.size:
            low, high = min(low, float(x.min())), max(high, float(x.max()))
    state: list[list] = [[low, high, True, 0] for _ in ranks]  # lo, hi, hi included, values below lo
    found: dict[int, float] = {}
    while len(found) < len(ranks):
        open_ranks = [i for i in range(len(ranks)) if i not in found]
        for i in open_ranks:
            if state[i][0] == state[i][1]:
                found[i] = state[i][0]
        open_ranks = [i for i in open_ranks if i not in found]
        if not open_ranks:
            break
        edges = {i: np.linspace(state[i][0], state[i][1], BINS + 1) for i in open_ranks}
        counts = {i: np.zeros(BINS, np.int64) for i in open_ranks}
        lows = {i: np.full(BINS, np.inf) for i in open_ranks}
        highs = {i: np.full(BINS, -np.inf) for i in open_ranks}
        for x in values():
            for i in open_ranks:
                lo, hi, closed, _ = state[i]
                mine = x[(x >= lo) & ((x <= hi) if closed else (x < hi))]
                where = _bin(mine, edges[i])
                counts[i] += np.bincount(where, minlength=BINS)
                np.minimum.at(lows[i], where, mine)
                np.maximum.at(highs[i], where, mine)
        gather = []
        for i in open_ranks:
            cumulative = np.cumsum(counts[i])
            b = int(np.searchsorted(cumulative, ranks[i] - state[i][3], "right"))
            state[i][3] += int(cumulative[b] - counts[i][b])
            # the bin's own values span [low, high]: a bin of one value ends the search
            state[i][:3] = [float(lows[i][b]), float(highs[i][b]), True]
            if counts[i][b] <= GATHER and lows[i][b] < highs[i][b]:
                gather.append(i)
        if gather:
            picked: dict[int, list[np.ndarray]] = {i: [] for i in gather}
            for x in values():
                for i in gather:
                    lo, hi, closed, _ = state[i]
                    picked[i].append(x[(x >= lo) & ((x <= hi) if closed else (x < hi))])
            for i in gather:
                found[i] = float(np.sort(np.concatenate(picked[i]))[ranks[i] - state[i][3]])
    return [found[i] for i in range(len(ranks))]


def _bin(x: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Each value's bin among ``edges`` (``edges[b] <= x < edges[b + 1]``, the
    last bin closed), as ``np.searchsorted(edges, x, "right") - 1``: a guess
    from the spacing, corrected by a bin where rounding misplaced it."""
    last = edges.size - 2
    width = (edges[-1] - edges[0]) / (last + 1)
    b = np.zeros(x.size, np.int64) if width <= 0 else np.clip(((x - edges[0]) / width).astype(np.int64), 0, last)
    b -= (x < edges[b]) & (b > 0)
    b += (x >= edges[np.minimum(b + 1, last + 1)]) & (b < last)
    return b


def _median(values: Callable[[], Iterator[np.ndarray]], n: int) -> float:
    """``np.median`` of the values, exactly (the mean of the two middle ones for an even count)."""
    middle = _ranked(values, n, [(n - 1) // 2, n // 2] if n % 2 == 0 else [n // 2])
    return float(np.mean(middle))


def _robust_sd(values: Callable[[], Iterator[np.ndarray]], n: int) -> float:
    """``grid._robust_sd``: 1.4826 times the median absolute deviation."""
    if not n:
        return 0.0
    centre = _median(values, n)
    return float(1.4826 * _median(lambda: (np.abs(x - centre) for x in values()), n))


@dataclass(eq=False)
class _Slots:
    """Every stamp's slot ``k`` and logging run, as functions of the stamp:
    ``k = base + shift[run0]`` and ``run = rmap[run0]``, where ``run0``
    counts the intervals of two slots or more so far, and ``base`` is the
    running count of slots (``grid`` None) or the slot on a fitted line
    (``grid``: offsets by run, period, each run0's run)."""

    first_period: float
    rmap: np.ndarray
    shift: np.ndarray
    grid: tuple[np.ndarray, float, np.ndarray] | None = None
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def walker(self) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
        """A function of the blocks of stamps in turn: each block's slots and runs."""
        carry: list = [None, 0, 0.0]  # the last stamp, its run0 and its running count of slots

        def walk(s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            last, run0_last, k0_last = carry
            steps = np.empty(s.size)  # the intervals from the stamp before, in slots
            steps[0] = 0.0 if last is None else float(s[0]) - float(last)
            np.subtract(s[1:], s[:-1], out=steps[1:], dtype=np.float64)
            steps /= self.first_period
            np.rint(steps, out=steps)
            np.maximum(steps, 1.0, out=steps)  # as grid_slots: any advance is at least one slot
            if last is None:
                steps[0] = 0.0
            jumps = steps >= 2
            # a block within one run (most): its run's numbers taken once, not looked up a sample at a time
            run0: np.ndarray | int = run0_last + np.cumsum(jumps) if jumps.any() else run0_last
            if self.grid is None:
                base = k0_last + np.cumsum(steps)  # whole numbers: exact in any order
                k0_last = float(base[-1])
            else:
                offset, period, gmap = self.grid
                base = np.rint((s - offset[gmap[run0]]) / period)
                k0_last += float(steps.sum())
            carry[:] = [s[-1], int(run0 if isinstance(run0, int) else run0[-1]), k0_last]
            run = self.rmap[run0]
            return base + self.shift[run0], run if isinstance(run0, np.ndarray) else np.full(s.size, run)
        return walk


def _walked(stamps: Stamps, slots: _Slots) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray, int]]:
    """Blocks of (stamps, slots, runs), each led by the previous block's last
    sample (pairs across a boundary), and how many lead (0 or 1)."""
    walk = slots.walker()
    previous = None
    for s in stamps():
        k, run = walk(s)
        if previous is None:
            yield s, k, run, 0
        else:
            yield _led(previous[0], s), _led(previous[1], k), _led(previous[2], run), 1
        previous = (s[-1], k[-1], run[-1])


def _led(first: np.generic, rest: np.ndarray) -> np.ndarray:
    """``np.r_[first, rest]`` without its parsing of the arguments (thousands of blocks)."""
    out = np.empty(rest.size + 1, rest.dtype)
    out[0], out[1:] = first, rest
    return out


def _fit(stamps: Stamps, slots: _Slots, n_runs: int) -> tuple[float, np.ndarray]:
    """``grid._grid_fit``: least squares ``s = a_run + T k``; the samples per run kept in ``slots.counts``."""
    count, k_sum, s_sum = np.zeros(n_runs, np.int64), np.zeros(n_runs), np.zeros(n_runs)
    for s, k, run, lead in _walked(stamps, slots):
        np.add.at(count, run[lead:], 1)
        np.add.at(k_sum, run[lead:], k[lead:])
        np.add.at(s_sum, run[lead:], s[lead:].astype(np.float64))
    k_mean, s_mean = k_sum / count, s_sum / count
    den = num = 0.0
    for s, k, run, lead in _walked(stamps, slots):
        dk = k[lead:] - k_mean[run[lead:]]
        den += _dot(dk, dk)
        num += _dot(dk, s[lead:] - s_mean[run[lead:]])
    if den <= 0:
        raise _NotStreamed("no run spans two slots")
    slots.counts = count
    period = num / den
    return period, s_mean - period * k_mean


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b without BLAS (whose threads, started for each of thousands of blocks, cost more than the sum)."""
    return float(np.einsum("i,i->", a, b))


def _white_jitter(stamps: Stamps, slots: _Slots, period: float, offset: np.ndarray) -> float:
    """``grid.white_jitter``: the robust sd of successive residual differences
    within runs, over sqrt(2). The differences are computed once, kept in a
    temporary file (8 bytes each) for the passes of the medians."""
    with tempfile.TemporaryFile() as spill:
        n = 0
        for s, k, run, _ in _walked(stamps, slots):
            step = np.diff(grid_residuals(s, k, run, period, offset))[run[1:] == run[:-1]]
            spill.write(step.tobytes())
            n += step.size
        spill.flush()

        def steps() -> Iterator[np.ndarray]:
            for a in range(0, n, SPILL_BLOCK):
                yield np.frombuffer(os.pread(spill.fileno(), 8 * min(SPILL_BLOCK, n - a), 8 * a), np.float64)
        return _robust_sd(steps, n) / np.sqrt(2.0)


def _grid_slots(stamps: Stamps, n: int) -> tuple[_Slots, float, np.ndarray]:
    """``grid.grid_slots`` (three re-slotting iterations) from passes over the stamps."""
    def d() -> Iterator[np.ndarray]:
        previous = None
        for s in stamps():
            yield intervals(s if previous is None else np.r_[previous, s])
            previous = s[-1]
    first_period = _median(d, n - 1)
    n_runs0 = 1 + sum(int(np.count_nonzero(np.maximum(np.rint(x / first_period), 1.0) >= 2)) for x in d())
    slots = _Slots(first_period, np.arange(n_runs0), np.zeros(n_runs0))
    for _ in range(3):
        period, offset = _fit(stamps, slots, int(slots.rmap[-1]) + 1)
        jitter = _white_jitter(stamps, slots, period, offset)
        u_offset = np.maximum(jitter, 1.0) / np.sqrt(np.maximum(slots.counts.astype(np.float64), 1.0))
        slip = (offset[1:] - offset[:-1]) / period
        whole = np.rint(slip)
        tolerance = np.minimum(4 * np.hypot(u_offset[1:], u_offset[:-1]) + 1e-4 * period, period / 2)
        hold = np.abs(slip - whole) * period < tolerance
        slots.shift = np.r_[0.0, np.cumsum(np.where(hold, whole, 0.0))][slots.rmap]
        slots.rmap = np.r_[0, np.cumsum(~hold)][slots.rmap]
        period, offset = _fit(stamps, slots, int(slots.rmap[-1]) + 1)
        slots.grid, slots.shift = (offset, period, slots.rmap.copy()), np.zeros(n_runs0)
    period, offset = _fit(stamps, slots, int(slots.rmap[-1]) + 1)
    return slots, period, offset


@dataclass
class _Sums:
    """Sums over the residuals (and slots) that ``check_capture`` takes over whole arrays."""

    n: int = 0
    r: float = 0.0
    rr: float = 0.0
    k: float = 0.0
    high: float = -np.inf
    low: float = np.inf
    pairs: int = 0
    x: float = 0.0
    y: float = 0.0
    centred: np.ndarray = field(default_factory=lambda: np.zeros(5))  # (r - mean)^2, (k - mean)^2, xx, yy, xy


def _statistics(stamps: Stamps, slots: _Slots, period: float, offset: np.ndarray) -> _Sums:
    """Two passes: the residuals' spread, largest, sum of squares, the
    slots' scatter and the lag-1 sums within runs (``grid.lag1_within``);
    slots two samples share, or slots going back within a run, raise ``_NotStreamed``."""
    sums = _Sums()
    for s, k, run, lead in _walked(stamps, slots):
        r = grid_residuals(s, k, run, period, offset)
        within = run[1:] == run[:-1]
        slot = k.astype(np.int64)
        if np.any(within & (slot[1:] <= slot[:-1])) or np.any(run[1:] < run[:-1]):
            raise _NotStreamed("samples sharing a slot, or slots out of order")
        own = r[lead:]
        sums.n += own.size
        sums.r += float(own.sum())
        sums.rr += _dot(own, own)
        sums.k += float(k[lead:].sum())
        sums.high, sums.low = max(sums.high, float(own.max())), min(sums.low, float(own.min()))
        sums.pairs += int(np.count_nonzero(within))
        sums.x += float(r[:-1][within].sum())
        sums.y += float(r[1:][within].sum())
    r_mean, k_mean = sums.r / sums.n, sums.k / sums.n
    x_mean, y_mean = sums.x / max(sums.pairs, 1), sums.y / max(sums.pairs, 1)
    for s, k, run, lead in _walked(stamps, slots):
        r = grid_residuals(s, k, run, period, offset)
        within = run[1:] == run[:-1]
        x, y = r[:-1][within] - x_mean, r[1:][within] - y_mean
        dr, dk = r[lead:] - r_mean, k[lead:] - k_mean
        sums.centred += _dot(dr, dr), _dot(dk, dk), _dot(x, x), _dot(y, y), _dot(x, y)
    return sums


def _lag1(sums: _Sums) -> float:
    """``grid.lag1_within`` from the sums."""
    xx, yy, xy = sums.centred[2:]
    if sums.pairs <= 2 or xx <= 0 or yy <= 0:
        return 0.0
    return float(np.clip(xy / np.sqrt(xx * yy), -1.0, 1.0))


def _gaps(stamps: Stamps, slots: _Slots, period: float, offset: np.ndarray, regular: bool, refit: bool,
          capture: str, config: TimebaseConfig) -> Gaps:
    """``check_capture``'s empty slots and gaps (from the slots where the
    sampling is regular, else from the intervals); ``_NotStreamed`` if the
    stamps on the grid (``refit``) would go back."""
    missing, lengths, middles, last = 0, [], [], None
    for s, k, run, lead in _walked(stamps, slots):
        within = run[1:] == run[:-1]
        if regular:
            p = k.astype(np.int64)
            step = np.diff(p)
            counted = within & (step != 0)
            missing += int(np.sum(step, where=counted)) - int(counted.sum())
            at_gap = counted & (step > config.gap_min_slots)
            lengths.append(step[at_gap] - 1)
            middles.append(offset[run[1:][at_gap]] + period * (p[1:][at_gap] + p[:-1][at_gap]) / 2)
        else:
            d = intervals(s)
            holes = np.where(within & (d > 0), np.maximum(np.rint(d / period), 1.0) - 1, 0.0)
            missing += int(holes.sum())
            at_gap = holes >= config.gap_min_slots
            lengths.append(holes[at_gap])
            middles.append((s[1:][at_gap] + s[:-1][at_gap]) / 2)
        if refit:
            t = _on_grid(k[lead:], run[lead:], period, offset)
            if np.any(t[1:] < t[:-1]) or (last is not None and t[0] < last):
                raise _NotStreamed("stamps on the grid out of order")
            last = t[-1]
    return Gaps(capture, missing, missing + int(slots.counts.sum()), period / 1e9, np.concatenate(middles),
                np.concatenate(lengths), int(slots.rmap[-1]), config.gap_min_slots)


def _on_grid(k: np.ndarray, run: np.ndarray, period: float, offset: np.ndarray) -> np.ndarray:
    grid = offset[run]  # the regular time base, offset[run] + period * slot, as check_capture rounds it
    grid += period * k
    return np.rint(grid, out=grid).astype(np.int64)


def stream_grid(stamps: Stamps, n: int, capture: str, config: TimebaseConfig = TimebaseConfig()) -> StreamedTimebase | None:
    """``check_capture``'s outcome for a capture of ``n`` stamps, none
    repeated, read by ``stamps()`` a block at a time in as many passes as
    its fits and medians need; None where the in-memory check is needed
    (module docstring)."""
    if n < 3:
        return None
    try:
        slots, period, offset = _grid_slots(stamps, n)
        jitter = _white_jitter(stamps, slots, period, offset)
        sums = _statistics(stamps, slots, period, offset)
        spread = float(np.sqrt(sums.centred[0] / n))
        u_period = float(np.sqrt(sums.rr / max(n - 2, 1) / sums.centred[1])) / 1e9
        stats = GridStats(n, n, period, u_period, jitter, _lag1(sums), spread, max(sums.high, -sums.low))
        jittery, _, regular = stats.regularity(config)
        gaps = _gaps(stamps, slots, period, offset, regular, jittery and regular, capture, config)
    except _NotStreamed:
        return None
    findings, warnings, unrepairable, refit = grid_findings(stats, 0, 0, gaps, capture, config)

    def repairer() -> Repairer:
        walk = slots.walker()

        def repair(block):
            t_ns = block["t_ns"].to_numpy()
            k, run = walk(t_ns)
            return replaced(block, np.ones(t_ns.size, bool), _on_grid(k, run, period, offset))
        return repair if refit else (lambda block: block)

    return StreamedTimebase(capture, period / 1e9, findings, warnings, unrepairable, gaps, n, repairer)
