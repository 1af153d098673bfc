"""The time base of a capture read block by block:
``check.check_capture``'s findings and repairs for a capture whose stamps
are read in blocks, and the repair applied to its sample blocks in order.

``StreamedTimebase`` is the outcome, with no sample-length array where the
time base is streamed (``blockwise.grid``); ``held`` wraps the
in-memory ``CaptureTimebase`` (its keep mask and stamps) for captures the
streamed check does not take.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.timebase.check import CaptureTimebase, Finding, Gaps, findings_frame

Stamps = Callable[[], Iterator[np.ndarray]]
# a fresh repairer for one pass over the sample blocks in order: block in, repaired block out
Repairer = Callable[[pl.DataFrame], pl.DataFrame]


class NotSorted(Exception):
    """The repaired stamps are out of order: the capture must be sorted whole."""


@dataclass(frozen=True, eq=False)
class StreamedTimebase:
    """One capture's time base: what ``check_capture`` finds (the period,
    findings, warnings, why rotation fits are refused if they are, the
    gaps), the rows it keeps, and ``repairer()`` for each pass over the
    capture's sample blocks (dropped rows, replaced stamps)."""

    capture: str
    interval_s: float
    findings: tuple[Finding, ...]
    warnings: tuple[str, ...]
    unrepairable: str | None
    gaps: Gaps | None
    n_kept: int
    repairer: Callable[[], Repairer]

    def findings_table(self, dataset: str) -> pl.DataFrame:
        """The capture's rows of the ``timebase`` table, as ``repair_timebase`` gives them."""
        return findings_frame([{"dataset": dataset, "capture": self.capture, **f.__dict__} for f in self.findings])


def replaced(block: pl.DataFrame, keep: np.ndarray, t_ns: np.ndarray) -> pl.DataFrame:
    """``block`` with the rows ``keep`` and the stamps ``t_ns``, copied only as far as something changes."""
    block = block if keep.all() else block.filter(pl.Series(keep))
    if np.array_equal(block["t_ns"].to_numpy(), t_ns):
        return block
    return block.with_columns(t_ns=pl.Series(t_ns, dtype=pl.Int64))


def outcome(tb: CaptureTimebase, capture: str, repairer: Callable[[], Repairer] = lambda: lambda block: block) -> StreamedTimebase:
    """An in-memory outcome with ``repairer`` (default: blocks already repaired)."""
    return StreamedTimebase(capture, tb.interval_s, tb.findings, tb.warnings, tb.unrepairable, tb.gaps,
                            int(tb.t_ns.size), repairer)


def held(tb: CaptureTimebase, capture: str) -> StreamedTimebase:
    """The in-memory outcome (the capture's keep mask and stamps held whole)
    as a ``StreamedTimebase``; ``NotSorted`` if the repaired stamps need a sort."""
    if np.any(tb.t_ns[1:] < tb.t_ns[:-1]):
        raise NotSorted(capture)

    def repairer() -> Repairer:
        rows, out = 0, 0

        def repair(block: pl.DataFrame) -> pl.DataFrame:
            nonlocal rows, out
            keep = tb.keep[rows : rows + block.height]
            n = int(np.count_nonzero(keep))
            t_ns = tb.t_ns[out : out + n]
            rows, out = rows + block.height, out + n
            return replaced(block, keep, t_ns)
        return repair
    return outcome(tb, capture, repairer)


class AtTies:
    """A channel's values only where stamps repeat (``check_capture`` reads a
    channel only at ``tie`` and ``tie + 1``): the positions in ascending
    order and their values."""

    def __init__(self, positions: np.ndarray, values: np.ndarray):
        self.positions, self.values = positions, values

    def __getitem__(self, index: np.ndarray) -> np.ndarray:
        return self.values[np.searchsorted(self.positions, index)]


def loaded(stamps: Stamps) -> np.ndarray:
    """Every stamp of a capture, in one array (the captures the streamed check does not take)."""
    return np.concatenate([np.zeros(0, np.int64), *stamps()])

