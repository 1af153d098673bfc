"""``check.check_capture`` for a capture whose stamps are read in blocks,
with no sample-length array.

The grid ``t_k = a_run + T k`` (``timebase.grid``) is fitted as in memory,
``grid.grid_slots``'s iterations stopped at the same fixed point, from sums
that are additive over blocks. Every slot ``k`` and logging run is a
function of the stamp's sample number and of a few numbers per run
(``_Slots``): within a run of one-slot intervals the running count of
slots is the sample number plus the slots skipped before the run, so only
the runs' first sample numbers are kept; later the slots are re-read from
the fitted lines. The sums come in another order than in memory (per block,
then across blocks), so the fit equals the in-memory one to rounding. The
medians (first period, the robust jitter) are exact: up to ``HELD`` values
(a memory bound, not the capture's) they are held and ``np.median`` taken
as in memory; past that a histogram of the values narrows each rank to one
bin, whose values are then gathered (``_ranked``), each step one pass.

Captures with repeated stamps (duplicates, collisions to place) or whose
slots would need a sort are left to the in-memory check (``None``).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

from rotcal.blockwise.ranks import HELD, Collected, median
from rotcal.blockwise.timebase import Repairer, Stamps, StreamedTimebase, replaced
from rotcal.timebase.check import Gaps, GridStats, TimebaseConfig, grid_findings
from rotcal.timebase.grid import intervals

Runs = np.ndarray | int  # each sample's run, or the one run of a whole block


class _NotStreamed(Exception):
    """The capture needs the in-memory check."""


@dataclass(eq=False)
class _Slots:
    """Every stamp's slot ``k`` and logging run, as functions of its sample
    number ``i`` and stamp ``s``: ``run0`` counts the intervals of two slots
    or more before it (``starts``: each run0's first sample number), the
    run is ``rmap[run0]`` and ``k = base + shift[run0]``, where ``base`` is
    the running count of slots, ``i + extra[run0]`` (``grid`` None: every
    interval within a run0 is one slot), or the slot on a fitted line,
    ``rint((s - offset[gmap[run0]]) / period)`` (``grid``: offsets by run,
    period, each run0's run)."""

    starts: np.ndarray
    extra: np.ndarray
    rmap: np.ndarray
    shift: np.ndarray
    grid: tuple[np.ndarray, float, np.ndarray] | None = None
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    k_means: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n_runs(self) -> int:
        return int(self.rmap[-1]) + 1

    def at(self, s: np.ndarray, first: int) -> tuple[np.ndarray, Runs]:
        """The slots and runs of the stamps ``s``, sample numbers ``first`` on
        (the run an int where they lie in one: most blocks)."""
        m = s.size
        lo, hi = np.searchsorted(self.starts, [first, first + m - 1], "right") - 1
        run0: np.ndarray | int = int(lo)
        if hi > lo:
            cuts = np.r_[0, self.starts[lo + 1 : hi + 1] - first, m]
            run0 = np.repeat(np.arange(lo, hi + 1), np.diff(cuts))
        if self.grid is None:  # whole numbers: exact in any order
            k = np.arange(first, first + m, dtype=np.float64)
            k += self.extra[run0] + self.shift[run0]
        else:
            offset, period, gmap = self.grid
            k = s - offset[gmap[run0]]
            k /= period
            np.rint(k, out=k)
            k += self.shift[run0]
        run = self.rmap[run0]
        return k, (int(run) if isinstance(run0, int) else run)


def _by_run(total: np.ndarray, run: Runs, values: np.ndarray) -> None:
    """``total[run] += values`` one value after the other, as ``np.bincount``
    adds them in memory (a cumulative sum where the block is one run)."""
    if isinstance(run, int):
        total[run] = np.cumsum(_led(total[run], values))[-1]
    else:
        np.add.at(total, run, values)


def _within(run: Runs) -> np.ndarray | slice:
    """Which successive pairs lie within one run (a slice: all of them)."""
    return slice(None) if isinstance(run, int) else run[1:] == run[:-1]


def _walked(stamps: Stamps, slots: _Slots) -> Iterator[tuple[np.ndarray, np.ndarray, Runs, int]]:
    """Blocks of (stamps, slots, runs), each led by the previous block's last
    sample (pairs across a boundary), and how many lead (0 or 1)."""
    first, previous = 0, None
    for s in stamps():
        led = s if previous is None else _led(previous, s)
        lead = led.size - s.size
        k, run = slots.at(led, first - lead)
        yield led, k, run, lead
        first, previous = first + s.size, s[-1]


def _led(first: np.generic, rest: np.ndarray) -> np.ndarray:
    """``np.r_[first, rest]`` without its parsing of the arguments."""
    out = np.empty(rest.size + 1, rest.dtype)
    out[0], out[1:] = first, rest
    return out


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b without BLAS (whose threads, started for each of thousands of blocks, cost more than the sum)."""
    return float(np.einsum("i,i->", a, b))


def _first_slots(stamps: Stamps, n: int) -> _Slots:
    """``grid.grid_slots``'s first slots: the intervals' median is the first
    period; the intervals of two of its slots or more start a run."""
    def d() -> Iterator[np.ndarray]:
        previous = None
        for s in stamps():
            yield intervals(s if previous is None else _led(previous, s))
            previous = s[-1]
    if n - 1 <= HELD:
        held = Collected(n - 1)
        for x in d():
            held.add(x)
        first_period = held.median()
    else:
        first_period = median(d, n - 1)
    starts, extra, i = [np.zeros(1, np.int64)], [np.zeros(1)], 0
    for x in d():
        steps = np.rint(x / first_period)
        jump = np.flatnonzero(steps >= 2)
        starts.append(i + jump + 1)
        extra.append(steps[jump] - 1)
        i += x.size
    runs0 = np.concatenate(starts)
    return _Slots(runs0, np.cumsum(np.concatenate(extra)), np.arange(runs0.size), np.zeros(runs0.size))


def _fit(stamps: Stamps, slots: _Slots) -> tuple[float, np.ndarray]:
    """``grid._grid_fit``: least squares ``s = a_run + T k``; the samples and mean slot per run kept in
    ``slots.counts`` and ``slots.k_means``."""
    n_runs = slots.n_runs
    count, k_sum, s_sum = np.zeros(n_runs, np.int64), np.zeros(n_runs), np.zeros(n_runs)
    for s, k, run, lead in _walked(stamps, slots):
        own = run if isinstance(run, int) else run[lead:]
        if isinstance(own, int):  # whole numbers: exact in any order
            count[own] += s.size - lead
            k_sum[own] += k[lead:].sum()
        else:
            count += np.bincount(own, minlength=n_runs)
            k_sum += np.bincount(own, k[lead:], n_runs)
        _by_run(s_sum, own, s[lead:].astype(np.float64))
    k_mean, s_mean = k_sum / count, s_sum / count
    den = num = 0.0
    for s, k, run, lead in _walked(stamps, slots):
        own = run if isinstance(run, int) else run[lead:]
        dk = k[lead:] - k_mean[own]
        den += _dot(dk, dk)
        num += _dot(dk, s[lead:] - s_mean[own])
    if den <= 0:
        raise _NotStreamed("no run spans two slots")
    slots.counts, slots.k_means = count, k_mean
    period = num / den
    return period, s_mean - period * k_mean


@dataclass
class _Sums:
    """Sums over the residuals (and slots) that ``check_capture`` takes over whole arrays."""

    n: int = 0
    r: float = 0.0
    rr: float = 0.0
    high: float = -np.inf
    low: float = np.inf
    pairs: int = 0
    x: float = 0.0
    y: float = 0.0
    disordered: bool = False  # slots two samples share, or slots or runs going back
    centred: np.ndarray = field(default_factory=lambda: np.zeros(5))  # (r - mean)^2, (k - its run's mean)^2, xx, yy, xy

    def add(self, r: np.ndarray, k: np.ndarray, run: Runs, lead: int) -> None:
        """A block's residuals, slots and runs (``lead`` samples of the block before)."""
        within = _within(run)
        if not isinstance(run, int):
            self.disordered |= bool(np.any(run[1:] < run[:-1]))
        self.disordered |= bool(np.any(k[1:][within] <= k[:-1][within]))
        own = r[lead:]
        self.n += own.size
        self.r += float(own.sum())
        self.rr += _dot(own, own)
        self.high, self.low = max(self.high, float(own.max())), min(self.low, float(own.min()))
        x, y = r[:-1][within], r[1:][within]
        self.pairs += x.size
        self.x += float(x.sum())
        self.y += float(y.sum())


def _residuals(s: np.ndarray, k: np.ndarray, run: Runs, period: float, offset: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``grid.grid_residuals`` and ``s - a_run`` (the stamps from their run's line, whose slots re-read them)."""
    u = s - offset[run]
    return u - period * k, u


def _residual_pass(stamps: Stamps, slots: _Slots, n: int, period: float, offset: np.ndarray) -> tuple[float, bool, _Sums]:
    """One pass at the fitted grid: ``grid.white_jitter`` (the robust sd of
    successive residual differences within runs, over sqrt(2)); whether
    re-reading the slots from the lines leaves every one as it is
    (``grid_slots``'s fixed point); and the residuals' sums."""
    steps, steady, sums = Collected(n - 1), True, _Sums()
    try:
        for s, k, run, lead in _walked(stamps, slots):
            r, u = _residuals(s, k, run, period, offset)
            if steady:
                u /= period
                steady = np.array_equal(np.rint(u, out=u), k)
            steps.add(np.diff(r)[_within(run)])
            sums.add(r, k, run, lead)
        return steps.robust_sd() / np.sqrt(2.0), steady, sums
    finally:
        steps.close()


def _grid_slots(stamps: Stamps, n: int) -> tuple[_Slots, float, np.ndarray, float, _Sums]:
    """``grid.grid_slots`` from passes over the stamps, to its fixed point
    (at most three re-slotting iterations), with the jitter and residual
    sums ``check_capture`` takes at the final grid."""
    slots = _first_slots(stamps, n)
    period, offset = _fit(stamps, slots)
    for _ in range(3):
        jitter, steady, sums = _residual_pass(stamps, slots, n, period, offset)
        u_offset = np.maximum(jitter, 1.0) / np.sqrt(np.maximum(slots.counts.astype(np.float64), 1.0))
        slip = (offset[1:] - offset[:-1]) / period
        whole = np.rint(slip)
        tolerance = np.minimum(4 * np.hypot(u_offset[1:], u_offset[:-1]) + 1e-4 * period, period / 2)
        hold = np.abs(slip - whole) * period < tolerance
        if not hold.any() and steady:
            return slots, period, offset, jitter, sums  # a further pass would repeat this one exactly
        if hold.any():  # the runs whose line continues the one before's are joined
            slots.shift = np.r_[0.0, np.cumsum(np.where(hold, whole, 0.0))][slots.rmap]
            slots.rmap = np.r_[0, np.cumsum(~hold)][slots.rmap]
            period, offset = _fit(stamps, slots)
        slots.grid, slots.shift = (offset, period, slots.rmap.copy()), np.zeros(slots.rmap.size)
        period, offset = _fit(stamps, slots)
    jitter, _, sums = _residual_pass(stamps, slots, n, period, offset)
    return slots, period, offset, jitter, sums


def _centred(stamps: Stamps, slots: _Slots, period: float, offset: np.ndarray, sums: _Sums) -> None:
    """The second pass of the statistics: the residuals' and slots' scatter
    about their means and the lag-1 sums within runs (``grid.lag1_within``)."""
    r_mean = sums.r / sums.n
    x_mean, y_mean = sums.x / max(sums.pairs, 1), sums.y / max(sums.pairs, 1)
    for s, k, run, lead in _walked(stamps, slots):
        r, _ = _residuals(s, k, run, period, offset)
        within = _within(run)
        x, y = r[:-1][within] - x_mean, r[1:][within] - y_mean
        dr, dk = r[lead:] - r_mean, k[lead:] - slots.k_means[run if isinstance(run, int) else run[lead:]]
        sums.centred += _dot(dr, dr), _dot(dk, dk), _dot(x, x), _dot(y, y), _dot(x, y)


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
        within = np.ones(s.size - 1, bool) if isinstance(run, int) else run[1:] == run[:-1]
        runs = np.full(s.size, run) if isinstance(run, int) else run
        if regular:
            p = k.astype(np.int64)
            step = np.diff(p)
            counted = within & (step != 0)
            missing += int(np.sum(step, where=counted)) - int(counted.sum())
            at_gap = counted & (step > config.gap_min_slots)
            lengths.append(step[at_gap] - 1)
            middles.append(offset[runs[1:][at_gap]] + period * (p[1:][at_gap] + p[:-1][at_gap]) / 2)
        else:
            d = intervals(s)
            holes = np.where(within & (d > 0), np.maximum(np.rint(d / period), 1.0) - 1, 0.0)
            missing += int(holes.sum())
            at_gap = holes >= config.gap_min_slots
            lengths.append(holes[at_gap])
            middles.append((s[1:][at_gap] + s[:-1][at_gap]) / 2)
        if refit:
            t = _on_grid(k[lead:], run if isinstance(run, int) else run[lead:], period, offset)
            if np.any(t[1:] < t[:-1]) or (last is not None and t[0] < last):
                raise _NotStreamed("stamps on the grid out of order")
            last = t[-1]
    return Gaps(capture, missing, missing + int(slots.counts.sum()), period / 1e9, np.concatenate(middles),
                np.concatenate(lengths), slots.n_runs - 1, config.gap_min_slots)


def _on_grid(k: np.ndarray, run: Runs, period: float, offset: np.ndarray) -> np.ndarray:
    """The regular time base, ``offset[run] + period * k``, as ``check_capture`` rounds it."""
    grid = period * k
    grid += offset[run]
    return np.rint(grid, out=grid).astype(np.int64)


def stream_grid(stamps: Stamps, n: int, capture: str, config: TimebaseConfig = TimebaseConfig()) -> StreamedTimebase | None:
    """``check_capture``'s outcome for a capture of ``n`` stamps, none
    repeated, read by ``stamps()`` a block at a time in as many passes as
    its fits and medians need; None where the in-memory check is needed
    (module docstring)."""
    if n < 3:
        return None
    try:
        slots, period, offset, jitter, sums = _grid_slots(stamps, n)
        if sums.disordered:
            raise _NotStreamed("samples sharing a slot, or slots out of order")
        _centred(stamps, slots, period, offset, sums)
        spread = float(np.sqrt(sums.centred[0] / n))
        u_period = float(np.sqrt(sums.rr / max(n - 1 - slots.n_runs, 1) / sums.centred[1])) / 1e9
        stats = GridStats(n, n, period, u_period, jitter, _lag1(sums), spread, max(sums.high, -sums.low))
        jittery, _, regular = stats.regularity(config)
        gaps = _gaps(stamps, slots, period, offset, regular, jittery and regular, capture, config)
    except _NotStreamed:
        return None
    findings, warnings, unrepairable, refit = grid_findings(stats, 0, 0, gaps, capture, config)

    def repairer() -> Repairer:
        first = 0

        def repair(block):
            nonlocal first
            t_ns = block["t_ns"].to_numpy()
            k, run = slots.at(t_ns, first)
            first += t_ns.size
            return replaced(block, np.ones(t_ns.size, bool), _on_grid(k, run, period, offset))
        return repair if refit else (lambda block: block)

    return StreamedTimebase(capture, period / 1e9, findings, warnings, unrepairable, gaps, n, repairer)
