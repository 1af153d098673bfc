"""CSV captures (docs/inputs.md, "CSV captures", with ``[format]`` for loggers' layouts)."""

from __future__ import annotations

import io
import os
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError
from rotcal.ingest.files import open_capture
from rotcal.ingest.labels import label_columns
from rotcal.ingest.meta import CaptureSpec, CsvFormat

NUMERIC = ("t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
TEXT = ("axis",)
REQUIRED = ("u", "v", "w")
_SCAN_BLOCK = 1 << 20


def _blocks(fh: BinaryIO) -> Iterator[bytes]:
    fh.seek(0)
    while block := fh.read(_SCAN_BLOCK):
        yield block


def check_line_lengths(fh: BinaryIO, path: Path, max_line_bytes: int) -> None:
    """Refuse a file with a line longer than ``max_line_bytes``, reading it in
    fixed-size blocks so that a hostile file cannot exhaust memory."""
    run = 0  # bytes since the last newline
    for block in _blocks(fh):
        ends = np.flatnonzero(np.frombuffer(block, np.uint8) == 10)
        if ends.size:
            longest = max(run + int(ends[0]), int(np.diff(ends).max(initial=1)) - 1)
            run = len(block) - 1 - int(ends[-1])
        else:
            longest = run = run + len(block)
        if max(longest, run) > max_line_bytes:
            raise LimitError(f"a line is longer than the limit of {max_line_bytes} bytes", path=path)


def _commas(lines: bytes) -> bytes:
    """Whole lines with runs of blanks and tabs made one comma, and those that
    open or close a line dropped (a line ends at \\n, or at the end of the file)."""
    b = np.frombuffer(lines, np.uint8)
    blank = (b == 32) | (b == 9)
    edges = np.diff(blank.view(np.int8), prepend=0, append=0)
    first, past = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # each run of blanks: [first, past)
    opens = (first == 0) | (b[first - 1] == 10)
    closes = (past == b.size) | (b[np.minimum(past, b.size - 1)] == 10)
    keep = ~blank
    keep[first[~opens & ~closes]] = True
    return np.where(blank, np.uint8(44), b)[keep].tobytes()


def _whitespace_to_commas(fh: BinaryIO) -> bytes:
    """A whitespace-delimited file as comma-separated text, converted a block
    of whole lines at a time: about twice the file (the result and its parts)
    and a few times the block, where regular expressions over the whole text
    took up to 40 times the file (a bytes object per token)."""
    parts, tail = [], b""
    for block in _blocks(fh):
        cut = block.rfind(b"\n") + 1
        if cut:
            parts.append(_commas(tail + block[:cut]))
            tail = block[cut:]
        else:
            tail += block  # a line longer than a block: check_line_lengths bounds it
    if tail:
        parts.append(_commas(tail))
    return b"".join(parts)


def _comma_source(fh: BinaryIO, fmt: CsvFormat) -> bytes | BinaryIO:
    return _whitespace_to_commas(fh) if fmt.delimiter == "whitespace" else fh


def _unreadable(exc: Exception, source: bytes | BinaryIO, path: Path) -> InputError:
    """Why polars could not parse the text, in a user's words."""
    if "utf-8" in str(exc).lower():
        return InputError("a value is not valid UTF-8 text (save the file as UTF-8)", path=path)
    quotes = source.count(b'"') if isinstance(source, bytes) else sum(b.count(b'"') for b in _blocks(source))
    if quotes % 2:
        return InputError('an unterminated quote (") makes the rest of the file one value', path=path)
    return InputError(f"cannot be read as CSV: {str(exc).splitlines()[0]}", path=path)


def _text(source: bytes | BinaryIO) -> BinaryIO:
    """``source`` for one more read from its start: polars reads an open file
    from where it stands."""
    if isinstance(source, bytes):
        return io.BytesIO(source)
    source.seek(0)
    return source


def _bad_value(source: bytes | BinaryIO, fmt: CsvFormat, wanted: dict[str, str], path: Path) -> InputError | None:
    """Re-read the numeric columns as text to name the first value that is not a number."""
    for name, file_col in wanted.items():
        if name not in NUMERIC:
            continue
        try:
            values = _read(source, fmt, {file_col: pl.String}, [file_col])[file_col]
        except pl.exceptions.ComputeError:  # not a value but the text itself: _unreadable says why
            return None
        bad = (values.cast(pl.Float64, strict=False).is_null() & values.is_not_null()).arg_true()
        if len(bad):
            row = int(bad[0])
            return InputError(f"column {name!r}, row {row + 1}: {values[row]!r} is not a number", path=path)
    return None


def _read(source: bytes | BinaryIO, fmt: CsvFormat, dtypes: dict, columns: list[str]) -> pl.DataFrame:
    sep = "," if fmt.delimiter == "whitespace" else fmt.delimiter
    if fmt.header:
        return pl.read_csv(
            _text(source), separator=sep, comment_prefix="#", columns=columns, schema_overrides=dtypes,
            infer_schema=False, raise_if_empty=False,
        )
    names = list(fmt.names or ())
    keep = [i for i, n in enumerate(names) if n in columns]
    # renamed after reading: polars' new_columns must name every column of the file, and a
    # logger's file may carry more columns than [format] names lists
    frame = pl.read_csv(
        _text(source), separator=sep, comment_prefix="#", has_header=False, columns=keep, infer_schema=False,
        raise_if_empty=False,
    )
    frame = frame.rename(dict(zip(frame.columns, [names[i] for i in keep])))
    return frame.with_columns(pl.col(c).cast(dtypes.get(c, pl.String)) for c in frame.columns)


def _header(source: bytes | BinaryIO, fmt: CsvFormat, path: Path) -> list[str]:
    if not fmt.header:
        return [n for n in fmt.names or () if n]
    sep = "," if fmt.delimiter == "whitespace" else fmt.delimiter
    try:
        return pl.read_csv(_text(source), separator=sep, comment_prefix="#", n_rows=0, infer_schema=False).columns
    except pl.exceptions.NoDataError:
        raise InputError("the file is empty", path=path) from None
    except pl.exceptions.ComputeError as exc:
        raise _unreadable(exc, source, path) from None


def read_csv_capture(path: Path, fmt: CsvFormat, spec: CaptureSpec | None, limits: Limits) -> pl.DataFrame:
    """One CSV capture as the columns of docs/inputs.md (``t`` in seconds, labels raw).

    The file is opened once, by its name as written (``open_capture``: never
    a glob pattern, never a FIFO), and every read goes through that handle.
    """
    with open_capture(path) as fh:
        if os.fstat(fh.fileno()).st_size == 0:
            raise InputError("the file is empty", path=path)
        check_line_lengths(fh, path, limits.max_line_bytes)
        return _capture(_comma_source(fh, fmt), fmt, spec, path)


def _capture(source: bytes | BinaryIO, fmt: CsvFormat, spec: CaptureSpec | None, path: Path) -> pl.DataFrame:
    # a header written "t, u, v, w" names its columns with the spaces around them
    present = {c.strip(): c for c in _header(source, fmt, path)}
    wanted = {name: present[fmt.file_column(name)] for name in (*NUMERIC, *TEXT) if fmt.file_column(name) in present}
    missing = [c for c in REQUIRED if c not in wanted]
    if "t" not in wanted and fmt.sample_rate_hz is None:
        missing.insert(0, "t")
    if missing:
        raise InputError(
            f"missing required column{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}"
            f" (columns found: {', '.join(sorted(present)) or 'none'})",
            path=path, hint="map the file's columns in dataset.toml [format] columns" if present else None,
        )
    pose_col = present.get(fmt.pose_column)
    both = [name for name, file_col in wanted.items() if file_col == pose_col]
    if both:
        raise InputError(f"dataset.toml [format] pose_column {fmt.pose_column!r} is the file's {both[0]!r} column too: "
                         "a column holds one kind of label", path=path)
    dtypes = {wanted[c]: (pl.String if c in TEXT else pl.Float64) for c in wanted}
    columns = list(dtypes) + ([pose_col] if pose_col else [])
    try:
        frame = _read(source, fmt, dtypes, columns)
    except pl.exceptions.ColumnNotFoundError:
        raise InputError(f"the file has fewer columns than the {len(fmt.names or ())} that dataset.toml [format] names lists",
                         path=path) from None
    except (pl.exceptions.ComputeError, pl.exceptions.InvalidOperationError) as exc:  # parsing, or the cast of a file without header
        raise _bad_value(source, fmt, wanted, path) or _unreadable(exc, source, path) from None
    # blank lines (a logger's trailing newlines) come back as rows of nulls: no sample, no error
    blank = pl.all_horizontal(pl.all().is_null())
    if frame.select(blank.any()).item():
        frame = frame.filter(~blank)
    frame = frame.rename({v: k for k, v in wanted.items()})
    if pose_col:
        frame = frame.rename({pose_col: "pose"})
    if frame.height == 0:
        raise InputError("the file has no samples", path=path)
    if "t" not in frame.columns:
        frame = frame.with_columns(t=pl.int_range(frame.height, dtype=pl.Int64).cast(pl.Float64) / fmt.sample_rate_hz)
    return label_columns(frame, spec, path)
