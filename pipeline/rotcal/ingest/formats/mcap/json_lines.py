"""JSON messages of an MCAP channel into a frame: each chunk's messages cut
out as JSON lines (``json_lines``), all of a channel's lines parsed together
by polars with the fields' types given (``parse_json_lines``). Anything
polars cannot read as one object a line raises ``Unsupported``: the caller
reads the file with the per-message path, which words the problem.
"""

from __future__ import annotations

import io
import json
from typing import IO

import numpy as np
import polars as pl

from rotcal.ingest.formats.mcap.records import Unsupported
from rotcal.model.physics import AXES

NUMBER_FIELDS = ("t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
TEXT_FIELDS = ("axis",)
JSON_TYPES = {name: pl.Float64 for name in NUMBER_FIELDS} | {name: pl.String for name in TEXT_FIELDS}


_NEWLINE, _COLON = 10, 58


def json_lines(raw: np.ndarray, data: np.ndarray, sizes: np.ndarray) -> tuple[bytes, int]:
    """The messages' bytes (``sizes`` bytes at ``data`` in ``raw``, ascending),
    one per line, and the colons in them (``parse_json_lines`` counts the
    keys by them, here while the chunk's lines are in the cache, not over
    all of a channel's lines at once): the span from the first to the last
    compressed by a mask of runs (each message and the byte after it, then
    the gap to the next), the bytes after the messages made newlines. A
    third less than gathering every byte by its own index (eight bytes of
    index per byte)."""
    n = data.size
    runs = np.empty(2 * n - 1, np.int64)
    runs[0::2] = sizes + 1
    runs[-1] -= 1  # the last message ends the span
    runs[1::2] = data[1:] - (data[:-1] + sizes[:-1]) - 1  # record headers: at least 31 bytes
    message = np.zeros(runs.size, bool)
    message[0::2] = True
    out = raw[int(data[0]) : int(data[-1] + sizes[-1])][np.repeat(message, runs)]
    out[np.cumsum(sizes + 1)[:-1] - 1] = _NEWLINE
    if np.count_nonzero(out == _NEWLINE) != n - 1:  # a message spans lines: not one object per line
        raise Unsupported("JSON message with a line break")
    return out.tobytes(), int(np.count_nonzero(out == _COLON))


def _read_json_lines(parts: list[bytes], n: int, types: dict) -> pl.DataFrame:
    try:
        # each chunk's lines a source (a BytesIO shares its bytes): no joined copy
        sources: list[IO[bytes]] = [io.BytesIO(part) for part in parts]
        frame = pl.read_ndjson(sources, schema=types)
    except Exception:  # noqa: BLE001 - any parser complaint: the per-message path words it
        raise Unsupported("JSON messages polars cannot parse as JSON lines") from None
    if frame.height != n:
        raise Unsupported("JSON messages other than one object a line")
    return frame


def _first_fields(text: bytes) -> dict:
    """``JSON_TYPES`` of the fields the first message has (all of them where it is not an object)."""
    try:
        first = json.loads(text[: text.find(b"\n") % (len(text) + 1)])
    except ValueError:
        first = None
    return {name: t for name, t in JSON_TYPES.items() if name in first} if isinstance(first, dict) else JSON_TYPES


def parse_json_lines(parts: list[bytes], n: int, colons: int) -> pl.DataFrame:
    """JSON lines (``parts``: each chunk's, from ``json_lines``, holding
    ``colons`` colons) parsed in one pass with the fields' types given: no
    inference over every line first, which took twice the parse. The fields
    of the first message are read first; when the text holds as many
    colons as values were read, no message has another key, null or not,
    and that frame is the answer. Else every field of ``JSON_TYPES`` is
    read, and a field is a column where some message has it.
    ``Unsupported`` where polars refuses a line, where a field is null
    wherever it appears (a key the types cannot tell from an absent one),
    and where an axis label is not x, y or z (polars writes a number given
    for text as text): the per-message path words those."""
    if n == 0:
        return pl.DataFrame()
    frame = _read_json_lines(parts, n, _first_fields(parts[0]))
    if frame.width * n - sum(frame.null_count().row(0)) != colons:
        frame = _read_json_lines(parts, n, JSON_TYPES)
        empty = [name for name, count in zip(frame.columns, frame.null_count().row(0)) if count == n]
        # a bare name: a quote in the needle slows the search tenfold
        if any(name.encode() in part for name in empty for part in parts):
            raise Unsupported("JSON field null in every message")
        frame = frame.drop(empty)
    if "axis" in frame.columns and not frame.select((pl.col("axis").is_in(AXES) | pl.col("axis").is_null()).all()).item():
        raise Unsupported("JSON axis label other than x, y or z")
    return frame
