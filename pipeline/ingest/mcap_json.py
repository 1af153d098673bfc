"""JSON messages of an MCAP channel into columns (``mcap_columns`` hands
over each chunk's messages): one object a message, gathered into JSON lines
by one mask over the chunk and parsed by polars with the fields' types
given, a chunk at a time on the channel's threads. What polars cannot take
raises ``Unsupported``: the per-message path words it."""

from __future__ import annotations

import json
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.ingest.mcap_records import Unsupported
from rotcal.model.physics import AXES

NUMBER_FIELDS = ("t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
JSON_TYPES = {name: pl.Float64 for name in NUMBER_FIELDS} | {"axis": pl.Enum(AXES)}


def _json_lines(raw: np.ndarray, data: np.ndarray, sizes: np.ndarray) -> tuple[bytes, int]:
    """The messages' bytes (``sizes`` bytes at ``data`` in ``raw``, ascending),
    one per line, and the colons among them: the span from the first to the
    last compressed by a mask of runs (each message and the byte after it,
    then the gap to the next), the bytes after the messages made newlines.
    A third less than gathering every byte by its own index (eight bytes of
    index per byte)."""
    n = data.size
    runs = np.empty(2 * n - 1, np.int64)
    runs[0::2] = sizes + 1
    runs[-1] -= 1  # the last message ends the span
    runs[1::2] = data[1:] - (data[:-1] + sizes[:-1]) - 1  # record headers: at least 31 bytes
    message = np.zeros(runs.size, bool)
    message[0::2] = True
    keep = np.repeat(message, runs)
    out = raw[int(data[0]) : int(data[-1] + sizes[-1])][keep]
    ends = np.cumsum(sizes + 1)[:-1] - 1
    out[ends] = 0
    if np.count_nonzero(out == 10):  # a message spans lines: not one object per line
        raise Unsupported("JSON message with a line break")
    out[ends] = 10
    return out.tobytes(), int(np.count_nonzero(out == ord(":")))


def _first_fields(text: bytes) -> dict:
    """``JSON_TYPES`` of the fields the first message has (all of them where it is not an object)."""
    try:
        first = json.loads(text[: text.find(b"\n") % (len(text) + 1)])
    except ValueError:
        first = None
    return {name: t for name, t in JSON_TYPES.items() if name in first} if isinstance(first, dict) else JSON_TYPES


@dataclass(frozen=True)
class JsonChunk:
    """One chunk's JSON messages of a channel: their log times, their text
    (one a line), its colons, and its parse under way (``json_chunk``)."""

    log_ns: np.ndarray
    text: bytes
    colons: int
    parse: Future


def json_chunk(raw: np.ndarray, data: np.ndarray, sizes: np.ndarray, log_ns: np.ndarray, pool: ThreadPoolExecutor) -> JsonChunk:
    """Start parsing one chunk's JSON messages (as ``_json_lines``) as JSON
    lines on a thread of ``pool``, with the types of the first message's
    fields given: no inference over every line first, which took twice the
    parse. Polars releases the GIL, so the chunks of a file are parsed side
    by side, and while later chunks are decompressed."""
    text, colons = _json_lines(raw, data, sizes)
    return JsonChunk(log_ns, text, colons, pool.submit(pl.read_ndjson, text, schema=_first_fields(text)))


def _json_parsed(chunk: JsonChunk, types: dict | None = None) -> pl.DataFrame:
    """The frame of ``chunk``'s parse (or of its text read again with ``types``)."""
    try:
        frame = chunk.parse.result() if types is None else pl.read_ndjson(chunk.text, schema=types)
    except Exception:  # noqa: BLE001 - any parser complaint: the per-message path words it
        raise Unsupported("JSON messages polars cannot parse as JSON lines") from None
    if frame.height != chunk.log_ns.size:
        raise Unsupported("JSON messages other than one object a line")
    return frame


def _chunk_frame(chunk: JsonChunk) -> pl.DataFrame:
    """One chunk's fields: its parse, if the text holds as many colons as
    values were read (a count at memory speed: then no message has another
    key, null or not). Else every field of ``JSON_TYPES`` is read again and
    the fields null in every message whose names occur nowhere in the text
    (a bare name: a quote in the needle slows the search tenfold) are left
    out: they are absent, not null."""
    frame = _json_parsed(chunk)
    if frame.width * frame.height - sum(frame.null_count().row(0)) == chunk.colons:
        return frame
    frame = _json_parsed(chunk, types=JSON_TYPES)
    counts = frame.null_count().row(0)
    return frame.drop(name for name, count in zip(frame.columns, counts) if count == frame.height and name.encode() not in chunk.text)


def json_frame(chunks: list[JsonChunk]) -> pl.DataFrame:
    """A channel's JSON messages, one column per field some message has, in
    ``JSON_TYPES`` order. ``Unsupported`` where Polars refuses a line, where
    a field is null wherever it appears (a key the types cannot tell from an
    absent one), and where an axis label is not x, y or z (the Enum refuses
    it; Polars would write a number given for text as text): the
    per-message path words those."""
    if not chunks:
        return pl.DataFrame()
    frame = pl.concat([_chunk_frame(chunk) for chunk in chunks], how="diagonal")
    if any(count == frame.height for count in frame.null_count().row(0)):
        raise Unsupported("JSON field null in every message")
    return frame.select(name for name in JSON_TYPES if name in frame.columns)
