"""Decoded columns kept on disk between the passes of a streamed run.

A streamed run reads a capture several times (the time base, the segment
sums, the residual statistics, the refits). Decompressing the chunks and
decoding the CDR messages again on each pass costs some 50 times more
than reading the decoded columns back from the page cache (a sample is 32
bytes: its stamp and three channels), so the first pass writes each
channel's columns here, batch by batch, and the later passes read them back
a piece at a time: the memory a pass needs stays bounded by the piece, not
by the capture (the files are read into fresh arrays, never mapped: mapped
pages would count as the process's resident memory).

The first pass over a capture's sample blocks keeps their labels too, as
the table's messages give them (``FrameSpill``: 17 bytes a sample), so
that the later passes read them back beside the samples instead of
mapping the messages onto the stamps and checking the labels again.

Each column is an anonymous temporary file (``tempfile.TemporaryFile``: no
name on disk, so it is removed however the run ends) in the run's
temporary directory (``tempfile.gettempdir()``, ``TMPDIR``), never in the
output directory.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable, Iterator, Mapping

import numpy as np
import numpy.typing as npt
import polars as pl

MARGIN_BYTES = 256 * 1024 * 1024  # free disk left to others beyond what the spill needs


def room_for(size: int) -> bool:
    """Whether the temporary directory has ``size`` bytes free, and the margin past them."""
    return shutil.disk_usage(tempfile.gettempdir()).free >= size * 1.1 + MARGIN_BYTES


class Spill:
    """Columns of fixed types (``dtypes``: name to type) appended batch by
    batch and read back in pieces of rows, in the order written."""

    def __init__(self, dtypes: Mapping[str, npt.DTypeLike]):
        self.dtypes = {name: np.dtype(d) for name, d in dtypes.items()}
        self.files = {name: tempfile.TemporaryFile(buffering=0) for name in self.dtypes}
        self.rows = 0

    def append(self, columns: dict[str, np.ndarray]) -> None:
        """One batch of every column (the same number of rows each)."""
        for name, file in self.files.items():
            values = np.ascontiguousarray(columns[name], self.dtypes[name])
            view = values.data.cast("B")
            while view.nbytes:  # a raw file may write part of a large buffer
                view = view[file.write(view):]
        self.rows += len(columns[next(iter(self.files))])

    def pieces(self, rows: int, names: tuple[str, ...] | None = None) -> Iterator[dict[str, np.ndarray]]:
        """The columns ``names`` (default all) ``rows`` rows at a time (the
        last piece fewer), each in arrays of their own."""
        names = tuple(self.files) if names is None else names
        for start in range(0, self.rows, rows):
            n = min(rows, self.rows - start)
            yield {name: self.read(name, start, n) for name in names}

    def read(self, name: str, start: int, n: int) -> np.ndarray:
        """Rows ``start`` to ``start + n`` of the column ``name``, in an array of their own."""
        out = np.empty(n, self.dtypes[name])
        view, offset = out.data.cast("B"), start * self.dtypes[name].itemsize
        while view.nbytes:
            got = os.preadv(self.files[name].fileno(), [view], offset)
            if got == 0:
                raise OSError(f"temporary file of {name!r} shorter than written")
            view, offset = view[got:], offset + got
        return out

    def close(self) -> None:
        for file in self.files.values():
            file.close()


class FrameSpill:
    """Frames of the columns ``columns`` (name to polars type: integers,
    floats, Enums) appended by one pass and read back, frame by frame and
    in the same heights, by the later ones: numbers as they are, an Enum
    by its codes (a null as the code past its categories)."""

    def __init__(self, columns: dict[str, pl.DataType]):
        self.columns = columns
        self.enums = {name: pl.Series([*t.categories, None], dtype=t) for name, t in columns.items() if isinstance(t, pl.Enum)}
        self.spill = Spill({name: np.dtype(np.uint8 if name in self.enums else np.int64 if t.to_python() is int else np.float64)
                            for name, t in columns.items()})
        self.heights: list[int] = []

    def append(self, frame: pl.DataFrame) -> bool:
        """One frame; False (nothing kept) where a number is null: a null is not kept."""
        numbers = [name for name in self.columns if name not in self.enums]
        if any(frame[name].null_count() for name in numbers):
            return False
        codes = {name: frame[name].to_physical().fill_null(len(e) - 1).to_numpy() for name, e in self.enums.items()}
        self.spill.append({**{name: frame[name].to_numpy() for name in numbers}, **codes})
        self.heights.append(frame.height)
        return True

    def join_last(self, count: int) -> None:
        """The last ``count`` frames appended read back as one."""
        if count > 1:
            self.heights[-count:] = [sum(self.heights[-count:])]

    def frames(self) -> Iterator[pl.DataFrame]:
        """The frames, as appended (or joined)."""
        rows = 0
        for height in self.heights:
            piece = {name: self.spill.read(name, rows, height) for name in self.columns}
            rows += height
            yield pl.DataFrame({name: self.enums[name].gather(piece[name]) if name in self.enums else
                                pl.Series(name, piece[name], dtype=t) for name, t in self.columns.items()})

    def close(self) -> None:
        self.spill.close()


def replayed(read: Callable[[], Iterator[pl.DataFrame]], columns: dict[str, pl.DataType], rows: int,
             rest: Callable[[], Iterator[pl.DataFrame]], kept: Callable[[], None]) -> Callable[[], Iterator[pl.DataFrame]]:
    """``read()``'s frames (``rows`` in all), anew for each pass: the first
    pass that reads them all keeps their ``columns`` where the temporary
    directory has room (``FrameSpill``), and the later passes give them
    back beside ``rest()``'s frames (the other columns, in the same heights)
    instead of reading; ``kept()`` is called once they are kept."""
    held: list[FrameSpill] = []
    row_bytes = sum(1 if isinstance(t, pl.Enum) else 8 for t in columns.values())

    def frames() -> Iterator[pl.DataFrame]:
        if held:
            for other, mine in zip(rest(), held[0].frames(), strict=True):
                yield other.hstack(mine.get_columns())
            return
        spill = FrameSpill(columns) if room_for(rows * row_bytes) else None
        try:
            for frame in read():
                if spill is not None and not spill.append(frame):
                    spill.close()
                    spill = None
                yield frame
            if spill is not None and not held:
                held.append(spill)
                kept()
        finally:
            if spill is not None and spill not in held:  # a pass left off, or another kept them first
                spill.close()
    return frames
