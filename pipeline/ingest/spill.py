"""Decoded columns kept on disk between the passes of a streamed run
(issue 16, item 1).

A streamed run reads a capture several times (the time base, the segment
sums, the residual statistics, the refits). Decompressing the chunks and
decoding the CDR messages again on each pass costs some 50 times more
than reading the decoded columns back from the page cache (a sample is 32
bytes: its stamp and three channels), so the first pass writes each
channel's columns here, batch by batch, and the later passes read them back
a piece at a time: the memory a pass needs stays bounded by the piece, not
by the capture (the files are read into fresh arrays, never mapped: mapped
pages would count as the process's resident memory).

Each column is an anonymous temporary file (``tempfile.TemporaryFile``: no
name on disk, so it is removed however the run ends) in the run's
temporary directory (``tempfile.gettempdir()``, ``TMPDIR``), never in the
output directory.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterator

import numpy as np

MARGIN_BYTES = 256 * 1024 * 1024  # free disk left to others beyond what the spill needs


def room_for(size: int) -> bool:
    """Whether the temporary directory has ``size`` bytes free, and the margin past them."""
    return shutil.disk_usage(tempfile.gettempdir()).free >= size * 1.1 + MARGIN_BYTES


class Spill:
    """Columns of fixed types (``dtypes``: name to type) appended batch by
    batch and read back in pieces of rows, in the order written."""

    def __init__(self, dtypes: dict[str, np.dtype]):
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
            yield {name: self._read(name, start, n) for name in names}

    def _read(self, name: str, start: int, n: int) -> np.ndarray:
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
