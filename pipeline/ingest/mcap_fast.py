"""MCAP records without a Python call per message.

A chunk is decompressed once; its message index records (which every
indexed MCAP writer puts after each chunk) give each channel's message
offsets, so the records are located with array arithmetic and checked to
tile the chunk exactly; the few other records in a chunk (schemas, channels)
are read one by one in the gaps. The messages of the kept channels become
columns in ``mcap_columns``.

Records are read by ``mcap_records``, as the per-message path reads them
(declared sizes checked, CRCs checked). Anything else (no message index or
one that declares more than it holds, messages outside chunks, other
layouts, damaged files) raises ``Unsupported``: the caller then reads the
file with the per-message path, which is also the one that words every
error, so both paths give the same samples and the same messages.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Schema

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.mcap_columns import MESSAGE_HEADER, DecodedTopic, Unsupported, decode_messages, gather
from rotcal.ingest.mcap_records import McapFile, chunk_data, chunk_records, parse_channel, parse_schema, top_records
from rotcal.ingest.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.parallel import cores

# Chunks are decompressed together (on a thread pool) up to this many bytes,
# compressed and decompressed, counted from their declared sizes; a batch
# holds one chunk at least (at most the record limit).
BATCH_BYTES = 32 * 1024 * 1024


@dataclass
class _State:
    where: McapFile
    topics: set[str]
    counts: dict[int, int]
    chunk_bytes: int
    schemas: dict[int, Schema] = field(default_factory=dict)
    found: dict[str, DecodedTopic] = field(default_factory=dict)
    keep: dict[int, DecodedTopic] = field(default_factory=dict)

    def schema(self, body: bytes | memoryview) -> None:
        record = parse_schema(body, self.where)
        self.schemas[record.id] = record

    def channel(self, body: bytes | memoryview) -> int | None:
        """Register a channel as the per-message path does (the first per
        topic); returns its id if its messages are to be decoded."""
        record = parse_channel(body, self.where)
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


@dataclass
class _Batch:
    """Chunks read and not yet decoded: (offset, body, message indexes) each,
    and their compressed and declared decompressed bytes."""

    chunks: list[tuple[int, bytes, list[bytes]]] = field(default_factory=list)
    size: int = 0

    def fits(self, body: bytes) -> bool:
        return not self.chunks or self.size + _footprint(body) <= BATCH_BYTES

    def add(self, offset: int, body: bytes) -> None:
        self.chunks.append((offset, body, []))
        self.size += _footprint(body)


def _footprint(body: bytes) -> int:
    """A chunk record's bytes and the bytes it declares it expands to (its
    ``uncompressed_size``, checked against the limit when it is decompressed)."""
    return len(body) + (struct.unpack_from("<Q", body, 16)[0] if len(body) >= 24 else 0)


def _inflate(chunk: tuple[int, bytes, list[bytes]], where: McapFile) -> np.ndarray:
    offset, body, _ = chunk
    return np.frombuffer(chunk_data(body, offset, where), np.uint8)


def _chunks(state: _State, batch: _Batch, mapper: Callable) -> None:
    """Decompress a batch of chunks with ``mapper`` (a thread pool's map:
    zstd, lz4 and crc32 release the GIL), then decode them in file order."""
    for raw, (offset, _, indexes) in zip(mapper(_inflate, batch.chunks, [state.where] * len(batch.chunks)), batch.chunks):
        _chunk(state, raw, offset, indexes)
    batch.chunks.clear()
    batch.size = 0


def _chunk(state: _State, raw: np.ndarray, offset: int, indexes: list[bytes]) -> None:
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
    if np.any(ends[:-1] > starts[1:]) or (ends.size and ends[-1] > size) or np.any(ends < starts):
        raise Unsupported("overlapping message records")
    # the other records (schemas, channels) sit in the gaps between messages
    gap_starts, gap_ends = np.r_[0, ends], np.r_[starts, size]
    defined_at = {}
    view = raw.data
    for lo, hi in zip(gap_starts[gap_starts < gap_ends].tolist(), gap_ends[gap_starts < gap_ends].tolist()):
        for opcode, pos, record in chunk_records(view[lo:hi], offset, state.where):
            if opcode == Opcode.MESSAGE:
                raise Unsupported("chunk record outside the message index")
            if opcode == Opcode.SCHEMA:
                state.schema(record)
            elif opcode == Opcode.CHANNEL and (cid := state.channel(record)) is not None:
                defined_at[cid] = lo + pos
    for channel_id, offsets in by_channel.items():
        topic = state.keep.get(channel_id)
        if topic is None or offsets.size == 0:
            continue  # the per-message path skips messages of channels it has not kept (yet)
        if offsets[0] < defined_at.get(channel_id, -1):
            raise Unsupported("messages before their channel record")
        decode_messages(topic, raw, offsets, channel_id, state.chunk_bytes)


def _message_index(body: bytes) -> tuple[int, int]:
    """(channel id, entries) of a message index record whose entries fit in it."""
    if len(body) < 6:
        raise Unsupported("message index shorter than its fields")
    channel_id, size = struct.unpack_from("<HI", body)
    if size % 16 or size > len(body) - 6:
        raise Unsupported("message index declares more entries than it holds")
    return channel_id, size // 16


def _message_counts(fh, where: McapFile) -> tuple[dict[int, int], int]:
    """Messages per channel id, from the message index records alone, and
    the bytes the chunks declare they expand to."""
    counts: dict[int, int] = {}
    chunk_bytes = 0
    for opcode, _, length in top_records(fh, where):
        if opcode == Opcode.MESSAGE_INDEX:
            channel_id, entries = _message_index(fh.read(length))
            counts[channel_id] = counts.get(channel_id, 0) + entries
        elif opcode == Opcode.CHUNK and length >= 24:
            chunk_bytes += struct.unpack("<QQQ", fh.read(24))[2]
    fh.seek(0)
    return counts, chunk_bytes


def read_topics(path: Path, topics: set[str], limits: Limits, workers: int = 0) -> dict[str, DecodedTopic]:
    """Every channel by topic, with the messages of ``topics`` and of any Imu
    or JointState channel decoded into columns; chunks are decompressed on
    ``parallel.cores(workers)`` threads (one: in this thread, no pool), at
    most ``BATCH_BYTES`` at a time.

    Raises ``Unsupported`` for anything but a chunked, indexed file of
    layouts this module decodes, damaged files included (the per-message
    path words their errors).
    """
    batch = _Batch()
    where = McapFile(path, limits)
    try:
        threads = cores(workers)
        with path.open("rb") as fh, ThreadPoolExecutor(threads) if threads > 1 else nullcontext() as pool:
            mapper = map if pool is None else pool.map
            state = _State(where, topics, *_message_counts(fh, where))
            for opcode, offset, length in top_records(fh, where):
                if opcode == Opcode.MESSAGE_INDEX and batch.chunks:
                    batch.chunks[-1][2].append(fh.read(length))
                    continue
                body = fh.read(length) if opcode in (Opcode.CHUNK, Opcode.SCHEMA, Opcode.CHANNEL) else b""
                if opcode == Opcode.CHUNK and batch.fits(body):
                    batch.add(offset, body)
                    continue
                if batch.chunks:
                    _chunks(state, batch, mapper)
                if opcode == Opcode.CHUNK:
                    batch.add(offset, body)
                elif opcode == Opcode.SCHEMA:
                    state.schema(body)
                elif opcode == Opcode.CHANNEL:
                    state.channel(body)
                elif opcode == Opcode.MESSAGE:
                    raise Unsupported("messages outside chunks")
    except (InputError, struct.error, ValueError) as exc:
        raise Unsupported(f"damaged MCAP ({exc})") from None
    for topic in state.keep.values():
        topic.finish()
    return state.found
