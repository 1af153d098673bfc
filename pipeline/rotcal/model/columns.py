"""A capture's outputs ``u, v, w`` as three columns, the way the sample
table holds them: the segmentation and the pose statistics read a capture
of millions of samples without an (n, 3) copy of it. Rows are gathered
only where a step reads them (a block, the samples between two dwells), in
the memory layout the (n, 3) array would have had, and a mean over rows
sums in that layout's order, so every value is the one the (n, 3) array
gives, bit for bit."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS

BLOCK = 1 << 18  # samples a block where a column is worked on a block at a time


@dataclass(frozen=True, eq=False)
class Outputs:
    """The columns of an (n, k) array of outputs. ``whole`` is that array
    where there is one (rows are then its views); otherwise rows are
    gathered in C order (``fortran`` False: ``np.column_stack``'s) or in
    Fortran order (a polars frame's ``to_numpy``)."""

    columns: tuple[np.ndarray, ...]
    whole: np.ndarray | None = None
    fortran: bool = False

    @staticmethod
    def of(y: np.ndarray | Outputs) -> Outputs:
        """``y`` itself, or the columns of the array ``y`` (views)."""
        if isinstance(y, Outputs):
            return y
        y = np.asarray(y)
        return Outputs(tuple(y[:, r] for r in range(y.shape[1])), y)

    @staticmethod
    def of_frame(samples: pl.DataFrame, rows: slice | np.ndarray = slice(None), fortran: bool = False) -> Outputs:
        """The rows ``rows`` of a sample table's ``u, v, w`` (views where its columns are one chunk each and
        ``rows`` a slice), gathered as ``np.column_stack`` (``fortran`` False) or ``select(...).to_numpy()`` would."""
        return Outputs(tuple(samples[c].to_numpy()[rows] for c in CHANNELS), fortran=fortran)

    def __len__(self) -> int:
        return self.columns[0].size

    @property
    def width(self) -> int:
        return len(self.columns)

    def rows(self, index: slice | np.ndarray) -> np.ndarray:
        """The rows ``index`` as an (m, k) array (a view of ``whole`` where it can be)."""
        if self.whole is not None:
            return self.whole[index]
        parts = [c[index] for c in self.columns]
        out = np.empty((parts[0].size, self.width), order="F" if self.fortran else "C")
        for r, part in enumerate(parts):
            out[:, r] = part
        return out

    def mean(self, start: int, stop: int) -> np.ndarray:
        """``y[start:stop].mean(axis=0)`` of the (n, k) array, without gathering the rows: numpy sums a
        C-ordered array's rows one after another, a Fortran-ordered one's columns pairwise."""
        if self.whole is not None:
            return self.whole[start:stop].mean(axis=0)
        if self.fortran:
            return np.array([c[start:stop].mean() for c in self.columns])
        return np.array([sequential_sum(c[start:stop]) for c in self.columns]) / (stop - start)

    def integer(self) -> bool:
        """Whether every output is a whole number (NaN is not), a block at a time."""
        return all(np.array_equal(c[a : a + BLOCK], np.round(c[a : a + BLOCK]))
                   for c in self.columns for a in range(0, c.size, BLOCK))


def sequential_sum(x: np.ndarray) -> float:
    """The sum of ``x`` from 0, adding one element after another (as numpy
    sums a column of a C-ordered array over its rows), a block at a time:
    each block's running sum starts from the sum so far."""
    total = np.zeros(1)
    for a in range(0, x.size, BLOCK):
        total = np.cumsum(np.concatenate([total, x[a : a + BLOCK]]))[-1:]
    return float(total[0])


def sample_step(t_ns: np.ndarray) -> float:
    """``np.median(np.diff(t_ns))``, the median sample period (ns), with one
    copy of the stamps' differences, not two (``np.median`` partitions a copy)."""
    return float(np.median(np.diff(t_ns), overwrite_input=True))


def steps_over(t_ns: np.ndarray, limit: float) -> np.ndarray:
    """``np.diff(t_ns) > limit``, a block at a time (no n-long differences)."""
    out = np.empty(max(t_ns.size - 1, 0), bool)
    for a in range(0, out.size, BLOCK):
        b = min(a + BLOCK, out.size)
        np.greater(np.diff(t_ns[a : b + 1]), limit, out=out[a:b])
    return out


def columns_of(y: np.ndarray | Outputs | Sequence[np.ndarray]) -> tuple[np.ndarray, ...]:
    """The columns of outputs given as an (n, k) array, ``Outputs`` or a sequence of columns."""
    if isinstance(y, Outputs):
        return y.columns
    if isinstance(y, np.ndarray):
        y = y.reshape(len(y), -1)
        return tuple(y[:, r] for r in range(y.shape[1]))
    return tuple(y)


def selected_rows(mask: np.ndarray) -> slice | np.ndarray:
    """The rows ``mask`` selects: a slice where they are one run (a single
    pose: indexing by it gives views, not copies), else the mask."""
    if not mask.any():
        return mask
    first, last = int(np.argmax(mask)), mask.size - int(np.argmax(mask[::-1]))
    return slice(first, last) if mask[first:last].all() else mask
