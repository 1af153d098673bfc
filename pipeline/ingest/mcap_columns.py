"""MCAP messages of fixed layout into columns, without a Python call per
message: ``mcap_fast`` hands over each kept channel's messages in a
decompressed chunk, and their fields become columns by strided views
or gathers (``fields``), each value copied once:

- ``sensor_msgs/msg/Imu`` in CDR whose ``frame_id`` keeps one length within
  a chunk (``ros2_cdr.imu_layout``);
- ``sensor_msgs/msg/JointState`` in CDR whose joint count and name lengths
  keep one layout within a chunk (``ros2_cdr.joint_layout``);
- JSON messages, one object each, parsed as JSON lines by polars with the
  fields' types given, a chunk at a time on the channel's threads.

Any other layout raises ``Unsupported``: the caller reads the file with the
per-message path instead.
"""

from __future__ import annotations

import json
import struct
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np
import polars as pl
from mcap.records import Channel, Schema

from rotcal.ingest.ros2_cdr import CDR_LE, imu_layout, joint_layout
from rotcal.ingest.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.model.physics import AXES

NUMBER_FIELDS = ("t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
JSON_TYPES = {name: pl.Float64 for name in NUMBER_FIELDS} | {"axis": pl.Enum(AXES)}
MESSAGE_HEADER = 31  # opcode u8, length u64, channel u16, sequence u32, log time u64, publish time u64
_CDR_LE = int(np.frombuffer(CDR_LE, "<u4")[0])


class Unsupported(Exception):
    """The file holds something this path does not decode."""


@dataclass
class DecodedTopic:
    """One channel's messages as columns, in file order.

    CDR channels have ``t_ns`` (header stamp, or log time where the stamp is
    zero, docs/inputs.md) and their fields; JSON channels ``log_ns`` and
    ``frame``, the messages' fields as parsed.
    """

    schema: Schema | None
    channel: Channel
    capacity: int = 0
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    frame: pl.DataFrame | None = None
    _filled: int = 0
    _parts: list = field(default_factory=list, repr=False)
    _pool: ThreadPoolExecutor | None = field(default=None, repr=False)

    @property
    def count(self) -> int:
        return len(self.frame) if self.frame is not None else self._filled

    @property
    def kind(self) -> str:
        if self.channel.message_encoding == "json":
            return "json"
        if self.channel.message_encoding == "cdr" and self.schema is not None:
            return {IMU_SCHEMA: "imu", JOINT_SCHEMA: "joint"}.get(self.schema.name, "other")
        return "other"

    def add(self, part: dict[str, np.ndarray]) -> None:
        """Copy one chunk's columns into the channel's arrays, allocated once
        for all its messages (counted from the message indexes), so no
        column is ever held twice."""
        if not self.columns:
            self.columns = {name: np.empty((self.capacity, *v.shape[1:]), v.dtype) for name, v in part.items()}
        k = len(part["t_ns"])
        for name, values in part.items():
            column = self.columns[name]
            if column.shape[1:] != values.shape[1:] or column.dtype != values.dtype:
                raise Unsupported("message layout changes between chunks")
            column[self._filled : self._filled + k] = values
        self._filled += k

    def add_json(self, raw: np.ndarray, data: np.ndarray, sizes: np.ndarray, log_ns: np.ndarray) -> None:
        """Start parsing one chunk's JSON messages (``json_chunk``) on the
        channel's threads, as many as Polars' (its share of the cores in a batch)."""
        if self._pool is None:
            self._pool = ThreadPoolExecutor(pl.thread_pool_size(), thread_name_prefix="rotcal-json")
        self._parts.append(json_chunk(raw, data, sizes, log_ns, self._pool))

    def finish(self) -> None:
        if self.kind == "json":
            chunks, self._parts = self._parts, []
            try:
                self.frame = json_frame(chunks)
            finally:
                if self._pool is not None:
                    self._pool.shutdown(cancel_futures=True)
            self.columns = {"log_ns": np.concatenate([c.log_ns for c in chunks]) if chunks else np.zeros(0, np.int64)}
            return
        self.columns = {name: column[: self._filled] for name, column in self.columns.items()} or {"t_ns": np.zeros(0, np.int64)}

    def take(self) -> dict[str, np.ndarray]:
        """The columns, handed over: the topic keeps no reference to them."""
        columns, self.columns = self.columns, {}
        return columns


@dataclass(frozen=True)
class Records:
    """Message records of one channel in a decompressed chunk ``raw``: where
    each starts, ``step`` (bytes) when they are evenly spaced (0 otherwise),
    and fields read ``skip`` bytes into each record (``data``: past the
    message header); ``uniform`` once checked to be messages of their
    channel, each ``step`` bytes, back to back (``mcap_fast``)."""

    raw: np.ndarray
    starts: np.ndarray
    step: int
    skip: int = 0
    uniform: bool = False

    @classmethod
    def at(cls, raw: np.ndarray, starts: np.ndarray) -> Records:
        """Records at ``starts`` in ascending order (as writers index them,
        else sorted: stable, a merge of ascending runs), their spacing found once."""
        if starts.size < 2:
            return cls(raw, starts, 1)
        step, spacing = int(starts[1] - starts[0]), np.diff(starts)
        if step > 0 and (spacing == step).all():
            return cls(raw, starts, step)
        return cls(raw, starts if (spacing > 0).all() else np.sort(starts, kind="stable"), 0)

    @property
    def count(self) -> int:
        return self.starts.size

    def data(self) -> Records:
        """The same records, fields counted from the message data."""
        return replace(self, skip=self.skip + MESSAGE_HEADER)

    def first(self, size: int) -> bytes:
        """The first record's ``size`` bytes (from ``skip``)."""
        start = int(self.starts[0]) + self.skip
        return self.raw[start : start + size].tobytes()


def fields(records: Records, offset: int, dtype: str, count: int = 1) -> np.ndarray:
    """``count`` values of ``dtype`` at byte ``offset`` of each record, as an
    (n,) or (n, count) array: a strided view of the chunk where the records
    are evenly spaced (a channel's run of messages of one size), else gathered
    through a view with a row at every byte; no record is copied whole, so
    each value is copied once, into its column (``DecodedTopic.add``)."""
    kind, raw, starts = np.dtype(dtype), records.raw, records.starts
    width = kind.itemsize * count
    shape = (starts.size,) if count == 1 else (starts.size, count)
    if starts.size == 0 or width == 0:
        return np.zeros(shape, kind)
    offset += records.skip
    if records.step:
        first = int(starts[0]) + offset
        return np.ndarray(shape, kind, raw, first, (records.step, kind.itemsize)[: len(shape)])
    window = np.ndarray((raw.size - width + 1, count), kind, raw, 0, (1, kind.itemsize))
    return window[starts + offset].reshape(shape)


def _stamp_or_log(data: Records, stamp_offset: int, log_ns: np.ndarray) -> np.ndarray:
    t_ns = fields(data, stamp_offset, "<i4").astype(np.int64)
    t_ns *= 1_000_000_000
    t_ns += fields(data, stamp_offset + 4, "<u4")
    return np.where(t_ns == 0, log_ns, t_ns)


def _check_cdr(data: Records) -> None:
    if np.any(fields(data, 0, "<u4") != _CDR_LE):
        raise Unsupported("CDR messages in another byte order")


def _decode_imu(data: Records, size: int, log_ns: np.ndarray) -> dict[str, np.ndarray]:
    """Imu messages of one ``size`` (``data``: their data) into columns."""
    if size < 16:  # the encapsulation, the stamp and the frame_id length
        raise Unsupported("Imu message shorter than its header")
    lay = imu_layout(int.from_bytes(data.first(16)[12:], "little"))
    _check_cdr(data)
    if size != lay.size or np.any(fields(data, 12, "<u4") != lay.frame_id_len):
        raise Unsupported("Imu frame_id of varying length")
    acc = fields(data, lay.linear_acceleration, "<f8", 3)
    return {"t_ns": _stamp_or_log(data, lay.stamp, log_ns), "x": acc[:, 0], "y": acc[:, 1], "z": acc[:, 2]}


def _joint_shape(message: bytes) -> tuple[int, tuple[int, ...], int, int]:
    """(frame_id length, name lengths, velocity count, effort count) of one
    JointState message, read field by field (once per chunk)."""
    body = memoryview(message)[4:]
    frame_len = struct.unpack_from("<I", body, 8)[0]
    off = (12 + frame_len + 3) // 4 * 4
    n = struct.unpack_from("<I", body, off)[0]
    off += 4
    lens = []
    for _ in range(n):
        lens.append(struct.unpack_from("<I", body, off)[0])
        off = (off + 4 + lens[-1] + 3) // 4 * 4
    counts = []
    for _ in range(3):
        counts.append(struct.unpack_from("<I", body, off)[0])
        start = (off + 4 + 7) // 8 * 8 if counts[-1] else off + 4
        off = start + 8 * counts[-1]
    if counts[0] != n or counts[1] not in (0, n) or min(lens, default=0) < 2:
        raise Unsupported("JointState with unnamed joints, or position or velocity counts other than its joint count")
    return frame_len, tuple(lens), counts[1], counts[2]


def _decode_joint(data: Records, size: int, log_ns: np.ndarray) -> dict[str, np.ndarray]:
    """JointState messages of one ``size`` (``data``: their data) into columns."""
    try:
        shape = _joint_shape(data.first(size))
    except struct.error:
        raise Unsupported("JointState message shorter than its fields") from None
    lay = joint_layout(*shape)
    if size != lay.size:
        raise Unsupported("JointState messages of varying layout")
    _check_cdr(data)
    if any(np.any(fields(data, o, "<u4") != v) for o, v in lay.counts):
        raise Unsupported("JointState messages of varying layout")
    n_vel = shape[2]
    names = np.column_stack([fields(data, o, f"S{k - 1}") for o, k in zip(lay.names, lay.name_lens)])
    position = fields(data, lay.position, "<f8", len(lay.names)).reshape(data.count, -1)
    velocity = fields(data, lay.velocity, "<f8", n_vel).reshape(data.count, n_vel)
    return {"t_ns": _stamp_or_log(data, lay.stamp, log_ns), "name": names, "position": position, "velocity": velocity}


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


def _message_sizes(records: Records, channel_id: int, kind: str) -> np.ndarray:
    """Each message's data size, checked: records of ``channel_id``, of one
    size unless JSON."""
    if records.uniform:
        return np.full(records.count, records.step - MESSAGE_HEADER)
    sizes = fields(records, 1, "<u8").astype(np.int64) - (MESSAGE_HEADER - 9)
    if np.any(sizes < 0):
        raise Unsupported("message record shorter than its header")
    if kind != "json" and np.any(sizes != sizes[0]):
        raise Unsupported("CDR messages of varying size")
    if np.any(fields(records, 9, "<u2") != channel_id):
        raise Unsupported("message index of another channel")
    return sizes


def decode_messages(topic: DecodedTopic, records: Records, channel_id: int, chunk_bytes: int) -> None:
    """Add one channel's message ``records`` in a decompressed chunk (each a
    complete record, by ``mcap_fast``) to ``topic``; the chunks of the file
    expand to ``chunk_bytes``."""
    sizes = _message_sizes(records, channel_id, topic.kind)
    # message indexes can claim any number of messages; the chunks hold no more than this many of this size
    topic.capacity = min(topic.capacity, chunk_bytes // (int(sizes[0]) + MESSAGE_HEADER))
    log_ns = fields(records, 15, "<i8")
    if topic.kind == "json":
        topic.add_json(records.raw, records.starts + MESSAGE_HEADER, sizes, log_ns.copy())
    elif topic.kind == "imu":
        topic.add(_decode_imu(records.data(), int(sizes[0]), log_ns))
    else:
        topic.add(_decode_joint(records.data(), int(sizes[0]), log_ns))
