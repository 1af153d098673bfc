"""MCAP records without a Python call per message.

A chunk is decompressed once; its message index records (which every
indexed MCAP writer puts after each chunk) give each channel's message
offsets, so the records are located with array arithmetic and checked to
tile the chunk exactly; the few other records in a chunk (schemas, channels)
are read one by one in the gaps. The messages of the kept channels become
columns in ``mcap_columns``.

Anything else (no message index, messages outside chunks, other layouts,
damaged files) raises ``Unsupported``: the caller then reads the file with
the per-message path, which is also the one that words every error, so both
paths give the same samples and the same messages.
"""

from __future__ import annotations

import io
import itertools
import struct
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import McapError
from mcap.opcode import Opcode
from mcap.records import Channel, Schema

from rotcal.config import Limits
from rotcal.ingest.mcap_columns import MESSAGE_HEADER, DecodedTopic, Unsupported, decode_messages, gather
from rotcal.ingest.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.parallel import cores

MAGIC = b"\x89MCAP0\r\n"
_BATCH_CHUNKS = 16  # chunks decompressed together (about 16 MiB)


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


def _chunks(state: _State, pending: list[tuple[bytes, list[bytes]]], mapper: Callable, limit: int) -> None:
    """Decompress a batch of chunks with ``mapper`` (a thread pool's map:
    zstd and lz4 release the GIL), then decode them in file order."""
    for raw, (_, indexes) in zip(mapper(_inflate, [body for body, _ in pending], itertools.repeat(limit)), pending):
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
    if starts.size and (starts[0] < 0 or starts[-1] > size - MESSAGE_HEADER):
        raise Unsupported("message index points outside its chunk")
    if np.any(raw[starts] != Opcode.MESSAGE):
        raise Unsupported("message index points at something other than a message")
    ends = starts + 9 + gather(raw, starts + 1, 8).view("<u8").ravel().astype(np.int64)
    if np.any(ends[:-1] > starts[1:]) or (ends.size and ends[-1] > size):
        raise Unsupported("overlapping message records")
    # the other records (schemas, channels) sit in the gaps between messages
    gap_starts, gap_ends = np.r_[0, ends], np.r_[starts, size]
    defined_at = {}
    for lo, hi in zip(gap_starts[gap_starts < gap_ends].tolist(), gap_ends[gap_starts < gap_ends].tolist()):
        while lo < hi:
            if lo + 9 > hi:
                raise Unsupported("truncated record in a chunk")
            opcode, length = struct.unpack_from("<BQ", raw.data, lo)
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
        decode_messages(topic, raw, offsets, channel_id)


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


def read_topics(path: Path, topics: set[str], limits: Limits, workers: int = 0) -> dict[str, DecodedTopic]:
    """Every channel by topic, with the messages of ``topics`` and of any Imu
    or JointState channel decoded into columns; chunks are decompressed on
    ``parallel.cores(workers)`` threads (one: in this thread, no pool).

    Raises ``Unsupported`` for anything but a chunked, indexed file of
    layouts this module decodes, damaged files included.
    """
    pending: list[tuple[bytes, list[bytes]]] = []  # chunks read, not yet decoded, each with its message indexes
    try:
        threads = cores(workers)
        with path.open("rb") as fh, ThreadPoolExecutor(threads) if threads > 1 else nullcontext() as pool:
            mapper = map if pool is None else pool.map
            state = _State(topics, _message_counts(fh, limits))
            for opcode, length in _records(fh, limits):
                if opcode == Opcode.MESSAGE_INDEX and pending:
                    pending[-1][1].append(_read(fh, length))
                    continue
                if opcode == Opcode.CHUNK and len(pending) < _BATCH_CHUNKS:
                    pending.append((_read(fh, length), []))
                    continue
                if pending:
                    _chunks(state, pending, mapper, limits.max_mcap_record_bytes)
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
