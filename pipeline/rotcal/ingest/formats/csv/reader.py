"""CSV captures (docs/inputs.md, "CSV captures", with ``[format]`` for loggers' layouts)."""

from __future__ import annotations

import dataclasses
import io
import mmap
import os
import re
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError
from rotcal.ingest.files import open_capture
from rotcal.ingest.formats.csv.layout import Layout, layout
from rotcal.ingest.labels import label_columns
from rotcal.ingest.meta import TIME_UNITS, CaptureSpec, CsvFormat, DatasetMeta
from rotcal.ingest.summaries import SUMMARY_COLUMNS, pose_summaries
from rotcal.model.physics import AXES, CHANNELS

NUMERIC = ("t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
TEXT = ("axis",)
REQUIRED = ("u", "v", "w")
AXIS_LABELS = pl.Enum(AXES)  # the sample table's axis type (tables.schema("samples"))
_SCAN_BLOCK = 1 << 20
ISO_DATE = re.compile(r"\s*\d{4}-\d\d-\d\d")


def _blocks(fh: BinaryIO) -> Iterator[bytes]:
    fh.seek(0)
    while block := fh.read(_SCAN_BLOCK):
        yield block


def lines_within(text: mmap.mmap | bytes, max_line_bytes: int) -> bool:
    """Whether every whole span of ``(max_line_bytes + 2) // 2`` bytes, laid
    end to end from the file's start, holds a newline: a longer line would
    cover one such span, so then none is (a search per span, each stopping at
    its first newline, where scanning every byte cost as much as a fifth of
    the parse)."""
    span = (max_line_bytes + 2) // 2
    return all(text.find(b"\n", start, start + span) >= 0 for start in range(0, len(text) - span + 1, span))


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


def _commas(lines: bytes, separator: int) -> bytes:
    """Whole lines with runs of blanks and tabs made one ``separator`` (a
    comma, or a semicolon between decimal commas), and those that open or
    close a line dropped (a line ends at \\n, or at the end of the file)."""
    b = np.frombuffer(lines, np.uint8)
    blank = (b == 32) | (b == 9)
    edges = np.diff(blank.view(np.int8), prepend=0, append=0)
    first, past = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # each run of blanks: [first, past)
    opens = (first == 0) | (b[first - 1] == 10)
    closes = (past == b.size) | (b[np.minimum(past, b.size - 1)] == 10)
    keep = ~blank
    keep[first[~opens & ~closes]] = True
    return np.where(blank, np.uint8(separator), b)[keep].tobytes()


def _whitespace_to_commas(fh: BinaryIO, separator: str) -> bytes:
    """A whitespace-delimited file as text separated by ``separator`` (a
    comma, or a semicolon where the numbers have decimal commas), converted a block
    of whole lines at a time: about twice the file (the result and its parts)
    and a few times the block, where regular expressions over the whole text
    took up to 40 times the file (a bytes object per token)."""
    parts, tail = [], b""
    for block in _blocks(fh):
        cut = block.rfind(b"\n") + 1
        if cut:
            parts.append(_commas(tail + block[:cut], ord(separator)))
            tail = block[cut:]
        else:
            tail += block  # a line longer than a block: check_line_lengths bounds it
    if tail:
        parts.append(_commas(tail, ord(separator)))
    return b"".join(parts)


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


def _numbers(values: pl.Expr, lay: Layout, strict: bool = True) -> pl.Expr:
    """Text as numbers with the file's decimal mark (not ``strict``: null where not one)."""
    return (values.str.replace(",", ".", literal=True) if lay.decimal_comma else values).cast(pl.Float64, strict=strict)


def _bad_value(source: bytes | BinaryIO, fmt: CsvFormat, lay: Layout, wanted: dict[str, str],
               path: Path) -> InputError | None:
    """Re-read the numeric columns as text to name the first value that is not a number."""
    for name, file_col in wanted.items():
        if name in TEXT:
            continue
        try:
            values = _read(source, fmt, lay, {file_col: pl.String}, [file_col])[file_col]
        except pl.exceptions.ComputeError:  # not a value but the text itself: _unreadable says why
            return None
        bad = (values.to_frame().select(_numbers(pl.first(), lay, strict=False)).to_series().is_null() & values.is_not_null()).arg_true()
        if len(bad):
            row, value = int(bad[0]), values[int(bad[0])]
            hint = ("; ISO 8601 date-times: set dataset.toml [format] time_unit = \"iso8601\""
                    if name == "t" and ISO_DATE.match(value) else "")
            return InputError(f"column {name!r}, row {row + 1}: {value!r} is not a number{hint}", path=path)
    return None


def _read(source: bytes | BinaryIO, fmt: CsvFormat, lay: Layout, dtypes: dict, columns: list[str]) -> pl.DataFrame:
    """``columns`` of the file (its header's names, or ``_file_columns``' positions) typed as ``dtypes``."""
    if fmt.header:
        return pl.read_csv(_text(source), **lay.read_options(), columns=columns, schema_overrides=dtypes,
                           infer_schema=False, raise_if_empty=False)
    keep = sorted(int(c) for c in columns)  # polars returns them in file order
    # renamed after reading: polars' new_columns must name every column of the file, and a
    # logger's file may carry more columns than [format] names lists
    frame = pl.read_csv(_text(source), **lay.read_options(), has_header=False, columns=keep, infer_schema=False,
                        raise_if_empty=False)
    frame = frame.rename(dict(zip(frame.columns, map(str, keep))))
    return frame.with_columns(_numbers(pl.col(c), lay) if dtypes.get(c) == pl.Float64 else pl.col(c).cast(dtypes.get(c, pl.String))
                              for c in frame.columns)


def _labels_typed(source: bytes | BinaryIO, fmt: CsvFormat, lay: Layout, dtypes: dict,
                  columns: list[str]) -> pl.DataFrame | None:
    """``_read`` with the axis labels parsed straight into the sample table's
    Enum (no column of strings to check and convert: a third of what
    ``label_columns`` cost); None for a file it cannot read so (a label
    written " X", a bad value, a short row): the caller reads it again with
    the labels as text and words what is wrong."""
    try:
        return _read(source, fmt, lay, dtypes, columns)
    except pl.exceptions.PolarsError:
        return None


def _file_columns(source: bytes | BinaryIO, fmt: CsvFormat, lay: Layout, path: Path) -> dict[str, str]:
    """Each column's name (the header's, stripped of spaces, or ``names``')
    -> how ``_read`` asks for it (the header's name, or the position)."""
    if not fmt.header:
        return {name: str(i) for i, name in enumerate(fmt.names or ()) if name}
    try:
        header = pl.read_csv(_text(source), **lay.read_options(), n_rows=0, infer_schema=False).columns
    except pl.exceptions.NoDataError:
        raise InputError("the file is empty" if not lay.skip_lines else
                         f"nothing after the {lay.skip_lines} lines of dataset.toml [format] skip_lines", path=path) from None
    except pl.exceptions.ComputeError as exc:
        raise _unreadable(exc, source, path) from None
    if fmt.names is None:
        # a header written "t, u, v, w" names its columns with the spaces around them
        return {c.strip(): c for c in header}
    if len(fmt.names) != len(header):
        raise InputError(f"dataset.toml [format] names lists {len(fmt.names)} names, the file's header has "
                         f"{len(header)} columns ({', '.join(c.strip() for c in header)})", path=path)
    return {name: c for name, c in zip(fmt.names, header) if name}


def read_csv_capture(path: Path, fmt: CsvFormat, spec: CaptureSpec | None, limits: Limits) -> pl.DataFrame:
    """One CSV capture as the columns of docs/inputs.md (``t`` in seconds, labels raw),
    or, for a file of pose summaries, their columns (``summaries.pose_summaries``).

    The file is opened once, by its name as written (``open_capture``: never
    a glob pattern, never a FIFO), and every read goes through that handle.
    """
    with open_capture(path) as fh:
        if os.fstat(fh.fileno()).st_size == 0:
            raise InputError("the file is empty", path=path)
        text = _mapped(fh)
        try:
            if text is None or not lines_within(text, limits.max_line_bytes):
                check_line_lengths(fh, path, limits.max_line_bytes)
            lay = layout(fh, fmt, path)
            source = _whitespace_to_commas(fh, lay.separator) if lay.whitespace else fh
            searched = source if isinstance(source, bytes) else text
            if lay.comment_prefix and searched is not None and searched.find(lay.comment_prefix.encode()) < 0:
                # no comment anywhere: polars' comment handling would cost a third of the parse
                lay = dataclasses.replace(lay, comment_prefix=None)
        finally:
            if text is not None:
                text.close()
        return _capture(source, fmt, lay, spec, path)


def _mapped(fh: BinaryIO) -> mmap.mmap | None:
    """The open file mapped read-only, searched at memchr speed without a
    copy; None where the file system cannot map it (then it is read)."""
    try:
        return mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ)
    except (OSError, ValueError):
        return None


def _capture(source: bytes | BinaryIO, fmt: CsvFormat, lay: Layout, spec: CaptureSpec | None,
             path: Path) -> pl.DataFrame:
    present = _file_columns(source, fmt, lay, path)
    summary = any(fmt.file_column(f"{c}_mean") in present for c in CHANNELS)
    names = SUMMARY_COLUMNS if summary else (*NUMERIC, *TEXT)
    wanted = {name: present[col] for name in names if (col := fmt.file_column(name)) in present}
    missing = [] if summary else [c for c in REQUIRED if c not in wanted]
    if not summary and "t" not in wanted and fmt.sample_rate_hz is None:
        missing.insert(0, "t")
    if missing:
        raise InputError(
            f"missing required column{'s' if len(missing) > 1 else ''} {', '.join(map(repr, missing))}"
            f" (columns found: {', '.join(sorted(present)) or 'none'})",
            path=path, hint="map the file's columns in dataset.toml [format] columns" if present else None,
        )
    pose_col = present.get(fmt.pose_column) if fmt.pose_column else None
    both = [name for name, file_col in wanted.items() if file_col == pose_col]
    if both:
        raise InputError(f"dataset.toml [format] pose_column {fmt.pose_column!r} is the file's {both[0]!r} column too: "
                         "a column holds one kind of label", path=path)
    iso = "t" in wanted and TIME_UNITS[fmt.time_unit] is None
    scaled = "t" in wanted and fmt.time_unit not in ("s", "iso8601")  # read as text: integer stamps stay exact
    dtypes = {wanted[c]: (pl.String if c in TEXT or (c == "t" and (iso or scaled)) else pl.Float64) for c in wanted}
    columns = list(dtypes) + ([pose_col] if pose_col else [])
    frame = _labels_typed(source, fmt, lay, dtypes | ({wanted["axis"]: AXIS_LABELS} if "axis" in wanted else {}), columns)
    try:
        frame = _read(source, fmt, lay, dtypes, columns) if frame is None else frame
    except pl.exceptions.ColumnNotFoundError:
        raise InputError(f"the file has fewer columns than the {len(fmt.names or ())} that dataset.toml [format] names lists",
                         path=path) from None
    except (pl.exceptions.ComputeError, pl.exceptions.InvalidOperationError) as exc:  # parsing, or the cast of a file without header
        numeric = {k: v for k, v in wanted.items() if not (k == "t" and (iso or scaled))}
        raise _bad_value(source, fmt, lay, numeric, path) or _unreadable(exc, source, path) from None
    # blank lines (a logger's trailing newlines) come back as rows of nulls: no sample, no error
    blank = pl.all_horizontal(pl.all().is_null())
    if min(frame.null_count().row(0)) and frame.select(blank.any()).item():  # counts are kept: no pass unless every column has a gap
        frame = frame.filter(~blank)
    frame = frame.rename({v: k for k, v in wanted.items()})
    if pose_col:
        frame = frame.rename({pose_col: "pose"})
    if frame.height == 0:
        raise InputError("the file has no samples" if not summary else "the file has no pose summaries", path=path)
    if summary:
        return pose_summaries(frame, path)
    if "t" not in frame.columns:
        frame = frame.with_columns(t=pl.int_range(frame.height, dtype=pl.Int64).cast(pl.Float64) / fmt.sample_rate_hz)
    elif iso:
        frame = iso_times(frame, path)
    elif scaled:
        frame = scaled_times(frame, lay, TIME_UNITS[fmt.time_unit] or 1.0, path)
    return label_columns(frame, spec, path)


def scaled_times(frame: pl.DataFrame, lay: Layout, per_second: float, path: Path) -> pl.DataFrame:
    """Time stamps in ``t`` (text) counted ``per_second`` as ``t_ns``: integer
    stamps exactly (Unix-epoch nanoseconds need all 63 bits), others by one
    rounding; with ``t`` in seconds for the range check of ``label_columns``."""
    text = pl.col("t").str.strip_chars()
    parsed = frame.select(_numbers(text, lay, strict=False).alias("value"), text.cast(pl.Int64, strict=False).alias("whole"),
                          pl.col("t").alias("text"))
    bad = (parsed["value"].is_null() & parsed["text"].is_not_null()).arg_true()
    if len(bad):
        raise InputError(f"column 't', row {int(bad[0]) + 1}: {parsed['text'][int(bad[0])]!r} is not a number", path=path)
    exact = parsed["whole"].null_count() == parsed["text"].null_count()
    ns_per_unit = 1e9 / per_second
    t_ns = (parsed["whole"] * round(ns_per_unit) if exact
            else (parsed["value"] * ns_per_unit).round().cast(pl.Int64, strict=False))
    return frame.with_columns(t=parsed["value"] / per_second, t_ns=t_ns)


def iso_times(frame: pl.DataFrame, path: Path) -> pl.DataFrame:
    """ISO 8601 date-times in ``t`` (``T`` or a blank between date and time,
    an offset, ``Z`` or none: UTC) as ``t_ns``, nanoseconds since the Unix epoch."""
    text = pl.col("t").str.strip_chars().str.replace(r"^(\d{4}-\d\d-\d\d) ", "${1}T").str.replace(r"Z$", "+00:00")
    text = pl.when(text.str.contains(r"[+-]\d\d:?\d\d$")).then(text).otherwise(text + "+00:00")
    stamps = text.str.to_datetime("%Y-%m-%dT%H:%M:%S%.f%#z", time_unit="ns", time_zone="UTC", strict=False)
    parsed = frame.select(stamps.dt.epoch("ns").alias("t_ns"), pl.col("t").alias("text"))
    bad = parsed["t_ns"].is_null().arg_true()
    if len(bad):
        row = int(bad[0])
        text = parsed["text"][row]
        problem = " is empty" if text is None else f": {text!r} is not an ISO 8601 date-time"
        raise InputError(f"column 't', row {row + 1}{problem}", path=path)
    return frame.drop("t").with_columns(parsed["t_ns"])


def read_capture(path: Path, spec: CaptureSpec | None, meta: DatasetMeta, limits: Limits,
                 workers: int = 0) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """The registry's reader (``ingest.formats``): ``read_csv_capture`` with the dataset's ``[format]``, no notes."""
    return read_csv_capture(path, meta.csv_format, spec, limits), ()
