"""A CSV capture read a block of lines at a time, in memory bounded by the
block: the CSV format's block reader (``ingest.formats``), ``open_capture``
gives a ``ingest.formats.blocks.RawStream`` whose blocks are exactly the samples
the in-memory reader (``reader.read_csv_capture``) gives.

It takes a plain file: comma-separated with one header of the names of
docs/inputs.md (t, u, v, w and any of axis, rate_hz, angle_deg), the
default ``[format]``, no quote, comment or blank line, every label number
present. A first pass parses each block of lines, checks and labels it as
the in-memory reader does (``labels.label_columns``), checks the time order
across blocks, and keeps the canonical columns on disk (``spill.FrameSpill``,
41 bytes a sample); each later pass reads them back. Anything else, and
every fault, raises ``NotBlockwise``: the capture is read whole, so every
message names the row it always did.
"""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest import files
from rotcal.ingest.formats.blocks import COLUMNS, NotBlockwise, RawStream, read_whole
from rotcal.ingest.formats.csv.joined import JOINED_TYPES, PLAIN
from rotcal.ingest.formats.csv.layout import layout
from rotcal.ingest.formats.csv.reader import lines_within
from rotcal.ingest.labels import label_columns
from rotcal.ingest.meta import CaptureSpec, CsvFormat, DatasetMeta
from rotcal.ingest.spill import FrameSpill, room_for
from rotcal.tables import conform, schema

READ_BYTES = 1 << 24  # the file read this many bytes at a time
PIECE_LINES = 1 << 18  # lines parsed at a time
_STAMP_BLOCK = 1 << 16  # stamps read back a block at a time for the time base
TAKEN = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg")  # header names the block reader takes


def message_counts(path: Path, limits: Limits) -> list[int]:
    """The capture's rows (its lines after the header), counted without parsing."""
    lines, last = 0, b"\n"
    try:
        with files.open_capture(path) as fh:
            while chunk := fh.read(READ_BYTES):
                lines += chunk.count(b"\n")
                last = chunk[-1:]
    except (InputError, OSError):
        return []
    return [max(lines + (last != b"\n") - 1, 0)]


def _line_blocks(fh, sizes: list[int], max_line_bytes: int) -> Iterator[bytes]:
    """The file's lines after the header, ``sizes[0]`` lines, then ``sizes[1]``,
    ... and round again (the last piece fewer), each ending in a newline; a
    line past ``max_line_bytes`` is not held (``NotBlockwise``: the whole
    reader refuses it in bounded memory)."""
    pending, k = b"", 0
    while True:
        chunk = fh.read(READ_BYTES)
        pending += chunk
        if not chunk:
            if pending:
                yield pending if pending.endswith(b"\n") else pending + b"\n"
            return
        ends = np.flatnonzero(np.frombuffer(pending, np.uint8) == 10)
        start, end = 0, sizes[k] - 1
        while end < ends.size:
            yield pending[start : ends[end] + 1]
            start = int(ends[end]) + 1
            k = (k + 1) % len(sizes)
            end += sizes[k]
        pending = pending[start:]
        if len(pending) - pending.rfind(b"\n") - 1 > max_line_bytes:
            raise NotBlockwise("a line longer than the limit")


def _header(fh, path: Path) -> bytes:
    """The header line, if the file is one the block reader takes."""
    fh.seek(0)
    if layout(fh, CsvFormat(), path) != PLAIN:
        raise NotBlockwise("not plain comma-separated text")
    fh.seek(0)
    header = fh.readline().rstrip(b"\r\n")
    names = header.decode("ascii", "replace").split(",")
    if len(set(names)) != len(names) or not set(names) <= set(TAKEN) or not {"t", "u", "v", "w"} <= set(names):
        raise NotBlockwise("columns other than t, u, v, w, axis, rate_hz, angle_deg")
    return header


def _labelled(text: bytes, header: bytes, spec: CaptureSpec | None, path: Path, limits: Limits,
              capture: str) -> pl.DataFrame:
    """One block's canonical columns, as the in-memory reader gives them, or ``NotBlockwise``."""
    if b'"' in text or b"#" in text or not lines_within(text, limits.max_line_bytes):
        raise NotBlockwise("quotes, comments or long lines")
    try:
        frame = pl.read_csv(io.BytesIO(header + b"\n" + text), schema_overrides=JOINED_TYPES, infer_schema=False,
                            comment_prefix=None, raise_if_empty=False)
        if frame.height != text.count(b"\n"):
            raise NotBlockwise("blank lines")
        labelled = label_columns(frame, spec, path).with_columns(capture=pl.lit(capture))
    except (pl.exceptions.PolarsError, InputError):
        raise NotBlockwise("a value the in-memory reader refuses: it words the error") from None
    return conform(labelled, "samples").select(COLUMNS)


def open_capture(path: Path, meta: DatasetMeta, spec: CaptureSpec | None, limits: Limits, workers: int, block: int,
                 capture: str, messages: int | None) -> RawStream:
    """The registry's block reader (``ingest.formats``; ``ingest.formats.blocks.open_stream``
    calls it): the capture's samples ``block`` rows at a time, the stamps
    and where they repeat; ``NotBlockwise`` for what it does not take (the
    module's docstring)."""
    if meta.csv_format != CsvFormat() or (spec is not None and spec.theta0_deg is not None):
        raise NotBlockwise("a [format] layout, or angles from [[capture]] theta0_deg")
    if not room_for(41 * (messages or 2 * path.stat().st_size)):
        raise NotBlockwise("too little free disk in the temporary directory to keep the decoded samples")
    spill = FrameSpill({c: schema("samples").polars_schema[c] for c in COLUMNS})
    at: list[np.ndarray] = []
    values: list[np.ndarray] = []
    last: tuple = ()  # the previous block's last sample (t_ns, u, v, w)
    n = 0
    try:
        with files.open_capture(path) as fh:
            header = _header(fh, path)
            source = "file" if {"axis", "rate_hz"} & set(header.decode().split(",")) else None
            # a block parsed in pieces (its text and temporaries a piece's), read back whole
            sizes = [min(PIECE_LINES, block - a) for a in range(0, block, PIECE_LINES)]
            pieces = 0  # of the block being read
            for text in _line_blocks(fh, sizes, limits.max_line_bytes):
                frame = _labelled(text, header, spec, path, limits, capture)
                if not spill.append(frame):
                    raise NotBlockwise("samples without a rate or an angle")
                pieces += 1
                if pieces == len(sizes):
                    spill.join_last(pieces)
                    pieces = 0
                t = frame["t_ns"].to_numpy()
                xyz = frame.select("u", "v", "w").to_numpy()
                if last:
                    if t[0] < last[0]:
                        raise NotBlockwise("time goes backwards: the in-memory reader words the error")
                    t, xyz = np.r_[last[0], t], np.vstack([last[1], xyz])
                tie = np.flatnonzero(t[1:] == t[:-1])
                if tie.size:  # both samples of a repeated stamp, for the time base's duplicate check
                    both = np.unique(np.r_[tie, tie + 1])
                    at.append(n - (1 if last else 0) + both)
                    values.append(xyz[both])
                last = (t[-1], xyz[-1])
                n += frame.height
    except BaseException:
        spill.close()
        raise
    spill.join_last(pieces)
    if n == 0:
        spill.close()
        raise NotBlockwise("no samples: the in-memory reader words the error")
    ties = None
    if at:
        positions, first = np.unique(np.concatenate(at), return_index=True)
        ties = (positions, np.concatenate(values)[first])
    if source is None and spec is not None and (spec.axis or spec.rate_hz is not None):
        source = "toml"

    def blocks() -> Iterator[pl.DataFrame]:
        return spill.frames()

    def stamps() -> Iterator[np.ndarray]:
        return (piece["t_ns"] for piece in spill.spill.pieces(_STAMP_BLOCK, ("t_ns",)))

    def whole() -> RawStream:
        return read_whole(path, meta, spec, limits, workers, capture)
    return RawStream(capture, n, source, meta.angle_source, (), whole, blocks, stamps, ties, _files=(spill,))
