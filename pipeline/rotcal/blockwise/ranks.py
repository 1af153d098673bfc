"""Exact medians of values read a block at a time, in memory bounded by
``HELD`` values, not by their number: the time base of
a capture read block by block (``blockwise.grid``) takes the median
interval and the robust scatter of the stamps (1.4826 times the median
absolute deviation, ``grid._robust_sd``) as ``np.median`` gives them.

Up to ``HELD`` values are held (``Collected``) and their median is
``np.median``'s; past that, a histogram of the values narrows each rank to
one bin, whose values are then gathered and sorted (``_ranked``), each step
one pass over the values (read again from their source or a temporary file).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator

import numpy as np

GATHER = 1 << 18  # values gathered and sorted to pick a rank
HELD = 1 << 24  # values up to which they are held (8 bytes each, 128 MB at most)
BINS = 1 << 12  # bins of a histogram narrowing a rank
SPILL_BLOCK = 1 << 18  # values read back from a temporary file at a time

Values = Callable[[], Iterator[np.ndarray]]


def _ranked(values: Values, n: int, ranks: list[int]) -> list[float]:
    """The values of ``ranks`` (0-based, in ascending order of value) among
    the ``n`` values ``values()`` yields, exactly, a few passes each.

    Each rank's candidates lie in a range of values [lo, hi) (hi included
    while it is the maximum), with ``below`` values under it; a histogram
    of the range finds the bin holding the rank, until the range holds few
    enough values to sort or a single value (the values past ``HELD``:
    fewer are held, ``Collected``)."""
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


def median(values: Values, n: int) -> float:
    """``np.median`` of the values, exactly (the mean of the two middle ones for an even count)."""
    middle = _ranked(values, n, [(n - 1) // 2, n // 2] if n % 2 == 0 else [n // 2])
    return float(np.mean(middle))


def robust_sd(values: Values, n: int) -> float:
    """``grid._robust_sd``: 1.4826 times the median absolute deviation."""
    if not n:
        return 0.0
    centre = median(values, n)
    return float(1.4826 * median(lambda: (np.abs(x - centre) for x in values()), n))


class Collected:
    """Values appended a block at a time (at most ``bound``): held in memory
    up to ``HELD`` of them, else written to an anonymous temporary file (8
    bytes a value) and read back for each pass of the medians."""

    def __init__(self, bound: int):
        self.n = 0
        self.held = np.empty(bound) if bound <= HELD else None
        self.file = None if self.held is not None else tempfile.TemporaryFile()

    def add(self, x: np.ndarray) -> None:
        if self.held is not None:
            self.held[self.n : self.n + x.size] = x
        else:
            assert self.file is not None
            self.file.write(np.ascontiguousarray(x, np.float64).tobytes())
        self.n += x.size

    def _blocks(self) -> Iterator[np.ndarray]:
        assert self.file is not None
        self.file.flush()
        for a in range(0, self.n, SPILL_BLOCK):
            size = min(SPILL_BLOCK, self.n - a)
            yield np.frombuffer(os.pread(self.file.fileno(), 8 * size, 8 * a), np.float64)

    def median(self) -> float:
        """``np.median`` of the values (held ones reordered in place)."""
        if self.held is not None:
            return float(np.median(self.held[: self.n], overwrite_input=True))
        return median(self._blocks, self.n)

    def robust_sd(self) -> float:
        """1.4826 times the median absolute deviation (``grid._robust_sd``;
        held values are overwritten)."""
        if not self.n:
            return 0.0
        if self.held is None:
            return robust_sd(self._blocks, self.n)
        x = self.held[: self.n]
        centre = np.median(x, overwrite_input=True)
        np.subtract(x, centre, out=x)
        np.abs(x, out=x)
        return float(1.4826 * np.median(x, overwrite_input=True))

    def close(self) -> None:
        if self.file is not None:
            self.file.close()
