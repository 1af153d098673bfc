"""A dataset of plain CSV captures read in one parse: the files' bodies
joined under their common header, checked as one table, labelled once.

A batch's default-plan dataset is fifteen small files; read one by one,
polars' fixed cost per read and per operation (a header read, a dozen
small selects each) outweighed the parse itself. Joined, the dataset costs
one parse and one pass of checks. Only what the per-file reader
(``reader.read_csv_capture``) would read the same way is joined; for
anything else, and for every fault, ``read_joined`` returns None and the
per-file reader reads the captures again, so every message names the file
and row it always did.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.files import open_capture
from rotcal.ingest.formats import by_name, format_of
from rotcal.ingest.formats.csv.layout import Layout, layout
from rotcal.ingest.formats.csv.reader import AXIS_LABELS, lines_within
from rotcal.ingest.labels import check_values, label_columns, nanoseconds
from rotcal.ingest.meta import CaptureSpec, CsvFormat
from rotcal.tables import conform

# the header names joined: numeric columns read as float, the axis label as the sample table's Enum
JOINED_TYPES: dict[str, pl.DataType | type[pl.DataType]] = {"t": pl.Float64, "u": pl.Float64, "v": pl.Float64, "w": pl.Float64, "axis": AXIS_LABELS,
                "rate_hz": pl.Float64, "angle_deg": pl.Float64, "temperature_c": pl.Float64}
PLAIN = Layout(",", whitespace=False, decimal_comma=False, skip_lines=0, comment_prefix="#")
# joined in memory only while small: a larger dataset's fixed costs are nothing beside its parse
MAX_JOINED_BYTES = 1 << 26
CSV = by_name("csv")


def _body(file: Path, text: bytes, header: bytes, limits: Limits) -> bytes | None:
    """The sample lines of one capture, ending with a newline, if the
    per-file reader would read it as plain comma-separated text under
    ``header``: lines within the limit, no comment or quote,
    the layout detected as plain commas. (A blank line is found by the
    joined read: a row short of the lines counted, or one without ``t``.)"""
    if not text.startswith(header + b"\n") or b"#" in text or b'"' in text or not lines_within(text, limits.max_line_bytes):
        return None
    body = text[len(header) + 1:]
    body += b"" if body.endswith(b"\n") else b"\n"
    if body == b"\n":
        return None
    try:
        return body if layout(io.BytesIO(text), CsvFormat(), file) == PLAIN else None
    except InputError:
        return None


def _texts(captures: list[tuple[Path, CaptureSpec | None]]) -> list[bytes] | None:
    """Each capture's bytes, None past ``MAX_JOINED_BYTES`` in all."""
    texts, total = [], 0
    for file, _ in captures:
        with open_capture(file) as fh:
            texts.append(fh.read(MAX_JOINED_BYTES + 1 - total))
        total += len(texts[-1])
        if total > MAX_JOINED_BYTES:
            return None
    return texts


def read_joined(captures: list[tuple[Path, CaptureSpec | None]], names: list[str], fmt: CsvFormat,
                limits: Limits) -> pl.DataFrame | None:
    """The canonical samples of ``captures`` (``names``: each one's name in
    the ``capture`` column), in time order, exactly as the per-file reader
    gives them; None unless every capture is a plain CSV file with the same
    header of docs/inputs.md names and no fault."""
    if fmt != CsvFormat() or any(spec is not None or format_of(file) is not CSV for file, spec in captures):
        return None
    texts = _texts(captures)
    if not texts or not texts[0]:
        return None
    header = texts[0].split(b"\n", 1)[0]
    columns = header.decode("ascii", "replace").split(",")
    if len(set(columns)) != len(columns) or not set(columns) <= JOINED_TYPES.keys() or not {"t", "u", "v", "w"} <= set(columns):
        return None
    bodies = [_body(file, text, header, limits) for (file, _), text in zip(captures, texts)]
    if any(body is None for body in bodies):
        return None
    rows = np.array([body.count(b"\n") for body in bodies if body is not None])
    try:
        frame = pl.read_csv(b"".join([header + b"\n", *(b for b in bodies if b is not None)]), schema_overrides=JOINED_TYPES,
                            infer_schema=False, comment_prefix=None, raise_if_empty=False)
        check_values(frame, captures[0][0])
    except (pl.exceptions.PolarsError, InputError):
        return None
    if frame.height != rows.sum():
        return None
    frame = frame.with_columns(t_ns=nanoseconds(pl.col("t")))
    t_ns = frame["t_ns"].to_numpy()
    back = t_ns[1:] < t_ns[:-1]  # compared, not differenced: a difference of two stamps may pass 2^63 ns
    starts = np.cumsum(rows)[:-1]  # each capture's first row: a step back into it is no fault
    if np.delete(back, starts - 1).any():
        return None
    capture = pl.Series("capture", names, pl.Categorical).gather(np.repeat(np.arange(len(rows), dtype=np.uint32), rows))
    if back.any():  # captures overlap in time: ordered as load_dataset orders them, stably
        order = np.argsort(t_ns, kind="stable")
        frame, capture = frame[order], capture.gather(order)
    try:
        samples = label_columns(frame, None, captures[0][0])
    except InputError:
        return None
    return conform(samples.with_columns(capture), "samples")
