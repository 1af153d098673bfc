"""MCAP decoding without a Python call per message.

A chunk is decompressed once; its message index records (which every
indexed MCAP writer puts after each chunk) give each channel's message
offsets, so the records are located with array arithmetic and checked to
tile the chunk exactly; the few other records in a chunk (schemas, channels)
are read one by one in the gaps. Messages of fixed layout become columns by
strided gathers:

- ``sensor_msgs/msg/Imu`` in CDR whose ``frame_id`` keeps one length within
  a chunk (``ros2_cdr.imu_layout``);
- ``sensor_msgs/msg/JointState`` in CDR whose joint count and name lengths
  keep one layout within a chunk (``ros2_cdr.joint_layout``);
- JSON messages, one object each, parsed together as JSON lines by polars.

Anything else (no message index, messages outside chunks, other layouts,
damaged files) raises ``Unsupported``: the caller then reads the file with
the per-message path, which is also the one that words every error, so both
paths give the same samples and the same messages.
"""

from __future__ import annotations

import io
import itertools
import os
import struct
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import numpy as np
import polars as pl
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Schema

from rotcal.config import Limits
from rotcal.ingest.ros2_cdr import CDR_LE, imu_layout, joint_layout

IMU_SCHEMA = "sensor_msgs/msg/Imu"
JOINT_SCHEMA = "sensor_msgs/msg/JointState"
MAGIC = b"\x89MCAP0\r\n"
_MESSAGE_HEADER = 31  # opcode u8, length u64, channel u16, sequence u32, log time u64, publish time u64
_CDR_LE = np.frombuffer(CDR_LE, np.uint8)
_BATCH_CHUNKS = 16  # chunks decompressed together (about 16 MiB)


class Unsupported(Exception):
    """The file holds something this path does not decode."""


@dataclass
class DecodedTopic:
    """One channel's messages as columns, in file order.

    CDR channels have ``t_ns`` (header stamp, or log time where the stamp is
    zero, contract section 2) and their fields; JSON channels ``log_ns`` and
    ``frame``, the messages' fields as parsed.
    """

    schema: Schema | None
    channel: Channel
    capacity: int = 0
    columns: dict[str, np.ndarray] = field(default_factory=dict)
    frame: pl.DataFrame | None = None
    _filled: int = 0
    _parts: list = field(default_factory=list, repr=False)

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

    def finish(self) -> None:
        if self.kind == "json":
            parts, self._parts = self._parts, []
            log_ns = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
            self.frame = _parse_json_lines(b"".join(p[1] for p in parts), log_ns.size)
            self.columns = {"log_ns": log_ns}
            return
        self.columns = {name: column[: self._filled] for name, column in self.columns.items()} or {"t_ns": np.zeros(0, np.int64)}

    def take(self) -> dict[str, np.ndarray]:
        """The columns, handed over: the topic keeps no reference to them."""
        columns, self.columns = self.columns, {}
        return columns


def _gather(raw: np.ndarray, starts: np.ndarray, width: int) -> np.ndarray:
    """The ``width`` bytes from each start, as an (n, width) array: a strided
    view where the starts are evenly spaced (one channel's run of messages
    of one size), else a gather."""
    step = int(starts[1] - starts[0]) if starts.size > 1 else 0
    if starts.size > 1 and step > 0 and starts[-1] == starts[0] + step * (starts.size - 1) and np.all(np.diff(starts) == step):
        view = np.lib.stride_tricks.as_strided(raw[starts[0] :], (starts.size, width), (step, 1), writeable=False)
        return view.copy()
    return raw[starts[:, None] + np.arange(width)]


def _field(data: np.ndarray, offset: int, dtype: str) -> np.ndarray:
    """Column ``offset`` of every message (rows of ``data``) as ``dtype``."""
    width = np.dtype(dtype).itemsize
    return np.ascontiguousarray(data[:, offset : offset + width]).view(dtype).ravel()


def _stamp_or_log(data: np.ndarray, stamp_offset: int, log_ns: np.ndarray) -> np.ndarray:
    t_ns = _field(data, stamp_offset, "<i4").astype(np.int64) * 1_000_000_000 + _field(data, stamp_offset + 4, "<u4")
    return np.where(t_ns == 0, log_ns, t_ns)


def _check_cdr(data: np.ndarray) -> None:
    if np.any(data[:, :4] != _CDR_LE):
        raise Unsupported("CDR messages in another byte order")


def _decode_imu(data: np.ndarray, log_ns: np.ndarray) -> dict[str, np.ndarray]:
    """Imu messages of one size (rows of ``data``) into columns."""
    lay = imu_layout(int(_field(data[:1], 12, "<u4")[0]))
    _check_cdr(data)
    if data.shape[1] != lay.size or np.any(_field(data, 12, "<u4") != lay.frame_id_len):
        raise Unsupported("Imu frame_id of varying length")
    acc = np.ascontiguousarray(data[:, lay.linear_acceleration : lay.linear_acceleration + 24]).view("<f8")
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


def _decode_joint(data: np.ndarray, log_ns: np.ndarray) -> dict[str, np.ndarray]:
    """JointState messages of one size (rows of ``data``) into columns."""
    try:
        shape = _joint_shape(data[0].tobytes())
    except struct.error:
        raise Unsupported("JointState message shorter than its fields") from None
    lay = joint_layout(*shape)
    _check_cdr(data)
    if data.shape[1] != lay.size or any(np.any(_field(data, o, "<u4") != v) for o, v in lay.counts):
        raise Unsupported("JointState messages of varying layout")
    n, n_vel = len(lay.names), shape[2]
    names = np.column_stack([_field(data, o, f"S{k - 1}") for o, k in zip(lay.names, lay.name_lens)])
    position = np.ascontiguousarray(data[:, lay.position : lay.position + 8 * n]).view("<f8")
    velocity = np.ascontiguousarray(data[:, lay.velocity : lay.velocity + 8 * n_vel]).view("<f8").reshape(-1, n_vel)
    return {"t_ns": _stamp_or_log(data, lay.stamp, log_ns), "name": names, "position": position, "velocity": velocity}


def _json_lines(raw: np.ndarray, data: np.ndarray, sizes: np.ndarray) -> bytes:
    """The messages' bytes, one per line."""
    total = int(sizes.sum())
    out_start = np.cumsum(sizes + 1) - (sizes + 1)
    src = np.repeat(data - out_start, sizes + 1) + np.arange(total + sizes.size)
    newline = out_start + sizes
    src[newline] = 0
    out = raw[src]
    if np.count_nonzero(out == 10):  # a message spans lines: not one object per line
        raise Unsupported("JSON message with a line break")
    out[newline] = 10
    return out.tobytes()


def _parse_json_lines(text: bytes, n: int) -> pl.DataFrame:
    if n == 0:
        return pl.DataFrame()
    try:
        frame = pl.read_ndjson(io.BytesIO(text), infer_schema_length=None)
    except Exception:  # noqa: BLE001 - any parser complaint: the per-message path words it
        raise Unsupported("JSON messages polars cannot parse as JSON lines") from None
    if frame.height != n or any(not (d.is_numeric() or d in (pl.Null, pl.String)) for d in frame.dtypes):
        raise Unsupported("JSON messages other than flat objects")
    return frame


@dataclass
class _State:
    topics: set[str]
    counts: dict[int, int]
    schemas: dict[int, Schema] = field(default_factory=dict)
    found: dict[str, DecodedTopic] = field(default_factory=dict)
    keep: dict[int, DecodedTopic] = field(default_factory=dict)

    def schema(self, body: bytes) -> None:
        record = Schema.read(ReadDataStream(io.BytesIO(body)))
        self.schemas[record.id] = record

    def channel(self, body: bytes) -> int | None:
        """Register a channel as the per-message path does (the first per
        topic); returns its id if its messages are to be decoded."""
        record = Channel.read(ReadDataStream(io.BytesIO(body)))
        if record.topic in self.found:
            return None
        topic = DecodedTopic(self.schemas.get(record.schema_id), record, self.counts.get(record.id, 0))
        self.found[record.topic] = topic
        kind = topic.schema.name if topic.schema is not None else ""
        if record.topic in self.topics or kind in (IMU_SCHEMA, JOINT_SCHEMA):
            if topic.kind == "other":
                raise Unsupported(f"channel {record.topic!r} has a layout this path does not decode")
            self.keep[record.id] = topic
            return record.id
        return None


def decompress_chunk(compression: str, data: bytes, size: int) -> bytes:
    """A chunk's records, decompressed to at most ``size`` + 1 bytes whatever
    the compressed frame claims (a frame header can declare any content
    size); a chunk that does not expand to exactly ``size`` bytes is refused."""
    if compression == "zstd":
        reader, out = zstandard.ZstdDecompressor().stream_reader(data), b""
        while len(out) <= size and (block := reader.read(size + 1 - len(out))):
            out += block
    elif compression == "lz4":
        out = lz4.frame.LZ4FrameDecompressor().decompress(data, max_length=size + 1)
    elif compression == "":
        out = data
    else:
        raise Unsupported(f"chunk compression {compression!r}")
    if len(out) != size:
        raise Unsupported(f"a chunk holds {len(out)} bytes where it declares {size}")
    return out


def _inflate(body: bytes, limit: int) -> np.ndarray:
    """A chunk record's decompressed records (none larger than ``limit``)."""
    head = struct.unpack_from("<QQQII", body, 0)
    size, name_len = head[2], head[4]
    if size > limit:
        raise Unsupported("chunk over the size limit")
    compression = body[32 : 32 + name_len].decode()
    (data_len,) = struct.unpack_from("<Q", body, 32 + name_len)
    payload = body[40 + name_len : 40 + name_len + data_len]
    if len(payload) != data_len:
        raise Unsupported("chunk shorter than its length")
    return np.frombuffer(decompress_chunk(compression, payload, size), np.uint8)


def _chunks(state: _State, pending: list[tuple[bytes, list[bytes]]], pool: ThreadPoolExecutor, limit: int) -> None:
    """Decompress a batch of chunks on every core (zstd and lz4 release the
    GIL), then decode them in file order."""
    for raw, (_, indexes) in zip(pool.map(_inflate, [body for body, _ in pending], itertools.repeat(limit)), pending):
        _chunk(state, raw, indexes)
    pending.clear()


def _chunk(state: _State, raw: np.ndarray, indexes: list[bytes]) -> None:
    """Decode one chunk's messages of the kept channels."""
    size = raw.size
    by_channel = {}
    for index in indexes:
        channel_id, length = struct.unpack_from("<HI", index, 0)
        pairs = np.frombuffer(index, "<u8", count=length // 16 * 2, offset=6).reshape(-1, 2)
        by_channel[channel_id] = np.sort(pairs[:, 1].astype(np.int64))
    starts = np.sort(np.concatenate([np.zeros(0, np.int64), *by_channel.values()]))
    if starts.size and (starts[0] < 0 or starts[-1] > size - _MESSAGE_HEADER):
        raise Unsupported("message index points outside its chunk")
    if np.any(raw[starts] != Opcode.MESSAGE):
        raise Unsupported("message index points at something other than a message")
    ends = starts + 9 + _gather(raw, starts + 1, 8).view("<u8").ravel().astype(np.int64)
    if np.any(ends[:-1] > starts[1:]) or (ends.size and ends[-1] > size):
        raise Unsupported("overlapping message records")
    # the other records (schemas, channels) sit in the gaps between messages
    gap_starts, gap_ends = np.r_[0, ends], np.r_[starts, size]
    defined_at = {}
    for lo, hi in zip(gap_starts[gap_starts < gap_ends].tolist(), gap_ends[gap_starts < gap_ends].tolist()):
        while lo < hi:
            if lo + 9 > hi:
                raise Unsupported("truncated record in a chunk")
            opcode, length = struct.unpack_from("<BQ", raw, lo)
            record = raw[lo + 9 : lo + 9 + length].tobytes()
            if lo + 9 + length > hi or opcode == Opcode.MESSAGE:
                raise Unsupported("chunk record outside the message index")
            if opcode == Opcode.SCHEMA:
                state.schema(record)
            elif opcode == Opcode.CHANNEL and (cid := state.channel(record)) is not None:
                defined_at[cid] = lo
            lo += 9 + length
    for channel_id, offsets in by_channel.items():
        topic = state.keep.get(channel_id)
        if topic is None or offsets.size == 0:
            continue  # the per-message path skips messages of channels it has not kept (yet)
        if offsets[0] < defined_at.get(channel_id, -1):
            raise Unsupported("messages before their channel record")
        sizes = _gather(raw, offsets + 1, 8).view("<u8").ravel().astype(np.int64) + 9
        if topic.kind == "json":
            head = _gather(raw, offsets, _MESSAGE_HEADER)
            data = None
        elif np.all(sizes == sizes[0]):  # fixed layout: each record copied once, fields are its columns
            head = _gather(raw, offsets, int(sizes[0]))
            data = head[:, _MESSAGE_HEADER:]
        else:
            raise Unsupported("CDR messages of varying size")
        if np.any(_field(head, 9, "<u2") != channel_id):
            raise Unsupported("message index of another channel")
        log_ns = _field(head, 15, "<i8")
        if topic.kind == "json":
            topic._parts.append((log_ns, _json_lines(raw, offsets + _MESSAGE_HEADER, sizes - _MESSAGE_HEADER)))
        elif topic.kind == "imu":
            topic.add(_decode_imu(data, log_ns))
        else:
            topic.add(_decode_joint(data, log_ns))


def _records(fh, limits: Limits):
    """(opcode, length) of each top-level record up to the footer, the file
    positioned at the record's body."""
    if fh.read(8) != MAGIC:
        raise Unsupported("no MCAP magic")
    while True:
        head = fh.read(9)
        if len(head) < 9:
            raise Unsupported("file ends inside a record")
        opcode, length = struct.unpack("<BQ", head)
        if length > limits.max_mcap_record_bytes:
            raise Unsupported("record over the size limit")
        yield opcode, length
        if opcode == Opcode.FOOTER:
            return


def _message_counts(fh, limits: Limits) -> dict[int, int]:
    """Messages per channel id, from the message index records alone."""
    counts: dict[int, int] = {}
    for opcode, length in _records(fh, limits):
        if opcode == Opcode.MESSAGE_INDEX:
            channel_id, size = struct.unpack("<HI", _read(fh, 6))
            counts[channel_id] = counts.get(channel_id, 0) + size // 16
            fh.seek(length - 6, io.SEEK_CUR)
        else:
            fh.seek(length, io.SEEK_CUR)
    fh.seek(0)
    return counts


def read_topics(path: Path, topics: set[str], limits: Limits) -> dict[str, DecodedTopic]:
    """Every channel by topic, with the messages of ``topics`` and of any Imu
    or JointState channel decoded into columns.

    Raises ``Unsupported`` for anything but a chunked, indexed file of
    layouts this module decodes, damaged files included.
    """
    pending: list[tuple[bytes, list[bytes]]] = []  # chunks read, not yet decoded, each with its message indexes
    try:
        with path.open("rb") as fh, ThreadPoolExecutor(os.cpu_count() or 1) as pool:
            state = _State(topics, _message_counts(fh, limits))
            for opcode, length in _records(fh, limits):
                if opcode == Opcode.MESSAGE_INDEX and pending:
                    pending[-1][1].append(_read(fh, length))
                    continue
                if opcode == Opcode.CHUNK and len(pending) < _BATCH_CHUNKS:
                    pending.append((_read(fh, length), []))
                    continue
                if pending:
                    _chunks(state, pending, pool, limits.max_mcap_record_bytes)
                if opcode == Opcode.CHUNK:
                    pending.append((_read(fh, length), []))
                elif opcode == Opcode.SCHEMA:
                    state.schema(_read(fh, length))
                elif opcode == Opcode.CHANNEL:
                    state.channel(_read(fh, length))
                elif opcode == Opcode.MESSAGE:
                    raise Unsupported("messages outside chunks")
                elif opcode == Opcode.FOOTER:
                    _read(fh, length)
                    if fh.read(8) != MAGIC:
                        raise Unsupported("no MCAP magic at the end")
                else:
                    _read(fh, length)
    except (McapError, struct.error, ValueError, EOFError, zstandard.ZstdError, RuntimeError) as exc:
        raise Unsupported(f"damaged MCAP ({exc})") from None
    for topic in state.keep.values():
        topic.finish()
    return state.found


def _read(fh, length: int) -> bytes:
    data = fh.read(length)
    if len(data) != length:
        raise Unsupported("file ends inside a record")
    return data
