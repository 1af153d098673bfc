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
from collections.abc import Callable, Generator, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Schema

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.mcap_columns import MESSAGE_HEADER, DecodedTopic, Unsupported, decode_messages, fields
from rotcal.ingest.mcap_records import McapFile, chunk_data, chunk_records, parse_channel, parse_schema, top_records
from rotcal.ingest.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.parallel import cores

# Chunks are decompressed together (on a thread pool) up to this many bytes,
# compressed and decompressed, counted from their declared sizes, in two
# batches (one decoded while the next is decompressed); a batch holds one
# chunk at least (at most the record limit).
BATCH_BYTES = 32 * 1024 * 1024


@dataclass
class _State:
    where: McapFile
    topics: set[str]
    counts: dict[int, int]
    chunk_bytes: int
    # two batches' decompressed chunks: one decoded while the next is decompressed
    buffers: list[np.ndarray] = field(default_factory=lambda: [np.empty(0, np.uint8)] * 2)
    turn: int = 0
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
        return not self.chunks or self.size + len(body) + _declared(body) <= BATCH_BYTES // 2  # two in flight

    def add(self, offset: int, body: bytes) -> None:
        self.chunks.append((offset, body, []))
        self.size += len(body) + _declared(body)


def _declared(body: bytes) -> int:
    """The bytes a chunk record declares it expands to (its ``uncompressed_size``)."""
    return struct.unpack_from("<Q", body, 16)[0] if len(body) >= 24 else 0


def _inflate(out: memoryview, chunk: tuple[int, bytes, list[bytes]], where: McapFile) -> None:
    offset, body, _ = chunk
    chunk_data(body, offset, where, out)


@dataclass
class _Flight:
    """A batch whose chunks are being decompressed side by side into ``raw``
    (chunk ``c`` from ``bases[c]``): ``done`` yields as each one is."""

    raw: np.ndarray
    bases: np.ndarray
    indexes: list[list[bytes]]
    done: Iterator
    size: int


def _launch(state: _State, batch: _Batch, mapper: Callable, overlap: bool) -> _Flight:
    """Start decompressing a batch with ``mapper`` (a thread pool's map, which
    submits every chunk at once: zstd and crc32 release the GIL) into a
    buffer: the other one of two where a batch in flight is to be decoded
    meanwhile (``overlap``), else the one last used (the other is freed)."""
    sizes = [_declared(body) for _, body, _ in batch.chunks]
    if max(sizes) > state.where.limits.max_mcap_record_bytes:
        raise Unsupported("a chunk declares more than the record limit")  # the per-message path says so
    bases = np.r_[0, np.cumsum(sizes, dtype=np.int64)]
    if overlap:
        state.turn ^= 1
    else:
        state.buffers[state.turn ^ 1] = np.empty(0, np.uint8)  # one batch at a time: one buffer
    if state.buffers[state.turn].size < bases[-1]:
        state.buffers[state.turn] = np.empty(int(bases[-1]), np.uint8)
    raw = state.buffers[state.turn][: bases[-1]]
    view = raw.data
    outs = [view[lo:hi] for lo, hi in zip(bases[:-1].tolist(), bases[1:].tolist())]
    chunks, size, batch.chunks, batch.size = batch.chunks, batch.size, [], 0
    done = mapper(_inflate, outs, chunks, [state.where] * len(chunks))
    return _Flight(raw, bases, [indexes for _, _, indexes in chunks], done, size)


def _relay(state: _State, batch: _Batch, mapper: Callable, flight: _Flight | None) -> _Flight:
    """Launch ``batch`` and decode the one in ``flight`` meanwhile, when both
    fit in ``BATCH_BYTES`` (else one after the other)."""
    if flight is not None and flight.size + batch.size > BATCH_BYTES:
        _land(state, flight)
        flight = None
    launched = _launch(state, batch, mapper, overlap=flight is not None)
    _land(state, flight)
    return launched


def _land(state: _State, flight: _Flight | None) -> None:
    """Wait for a batch's chunks, then decode their messages together."""
    if flight is not None:
        for _ in flight.done:
            pass
        _decode(state, flight.raw, flight.bases, flight.indexes)


def _ascending(offsets: np.ndarray) -> np.ndarray:
    """``offsets`` in ascending order: as writers index them, or sorted
    (stable sort: a merge of ascending runs, such as channels' concatenated offsets)."""
    return offsets if np.all(offsets[1:] > offsets[:-1]) else np.sort(offsets, kind="stable")


def _indexed(bases: np.ndarray, indexes: list[list[bytes]]) -> dict[int, np.ndarray]:
    """Each channel's message offsets in the batch's buffer (chunk ``c`` at
    ``bases[c]``), from the chunks' message indexes, each inside its chunk."""
    parts: dict[int, list[np.ndarray]] = {}
    for base, end, chunk_indexes in zip(bases[:-1].tolist(), bases[1:].tolist(), indexes):
        for index in chunk_indexes:
            channel_id, length = struct.unpack_from("<HI", index, 0)
            pairs = np.frombuffer(index, "<u8", count=length // 16 * 2, offset=6).reshape(-1, 2)
            offsets = _ascending(pairs[:, 1].astype(np.int64))
            if offsets.size and (offsets[0] < 0 or offsets[-1] > end - base - MESSAGE_HEADER):
                raise Unsupported("message index points outside its chunk")
            parts.setdefault(channel_id, []).append(offsets + base)
    return {channel_id: np.concatenate(p) for channel_id, p in parts.items()}


def _decode(state: _State, raw: np.ndarray, bases: np.ndarray, indexes: list[list[bytes]]) -> None:
    """Decode the messages of the kept channels in the decompressed chunks
    side by side in ``raw`` (chunk ``c`` from ``bases[c]``), checking that
    the indexed messages and the records between them tile each chunk."""
    by_channel = _indexed(bases, indexes)
    starts = _ascending(np.concatenate([np.zeros(0, np.int64), *by_channel.values()]))
    if np.any(raw[starts] != Opcode.MESSAGE):
        raise Unsupported("message index points at something other than a message")
    ends = starts + 9 + fields(raw, starts, 1, "<u8").astype(np.int64)
    # each chunk's bounds as empty records, so that no record spans two chunks and each gap lies in one
    at = np.searchsorted(starts, bases)
    starts, ends = np.insert(starts, at, bases), np.insert(ends, at, bases)
    if np.any(ends[:-1] > starts[1:]) or np.any(ends < starts):
        raise Unsupported("overlapping message records")
    # the other records (schemas, channels) sit in the gaps between messages
    gap = np.flatnonzero(ends[:-1] < starts[1:])
    defined_at = {}
    view = raw.data
    for lo, hi in zip(ends[gap].tolist(), starts[gap + 1].tolist()):
        for opcode, pos, record in chunk_records(view[lo:hi], 0, state.where):
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
    most ``BATCH_BYTES`` at a time, while the batch before is decoded.

    Raises ``Unsupported`` for anything but a chunked, indexed file of
    layouts this module decodes, damaged files included (the per-message
    path words their errors).
    """
    batch, flight = _Batch(), None
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
                    flight = _relay(state, batch, mapper, flight)
                if opcode != Opcode.CHUNK:  # a record outside chunks comes after the chunks before it
                    flight, landing = None, flight
                    _land(state, landing)
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


def iter_topic_batches(path: Path, topics: set[str], limits: Limits, workers: int = 0,
                       only: frozenset[int] = frozenset()) -> Generator[dict[str, DecodedTopic], None, dict[str, DecodedTopic]]:
    """``read_topics`` a batch of chunks at a time (issue 16, item 1): after
    each batch (at most ``BATCH_BYTES`` of chunks, decompressed on
    ``parallel.cores(workers)`` threads), the kept channels' messages in it,
    each a finished ``DecodedTopic`` holding that batch's columns only, by
    topic (channels without messages in the batch left out). Memory is one
    batch, whatever the file's length; a batch is decoded before the next is
    decompressed. It returns (``yield from``'s value) every channel by
    topic, as ``read_topics`` does, without their messages. Raises
    ``Unsupported`` as ``read_topics`` does, possibly after some batches.

    ``only`` (channel ids): once these channels are known, chunks holding
    none of their messages (by their message indexes) are not decompressed;
    a reader following one channel skips the others' chunks."""
    batch = _Batch()
    where = McapFile(path, limits)

    def wanted(indexes: list[bytes]) -> bool:
        return any(struct.unpack_from("<HI", index, 0)[0] in only and struct.unpack_from("<HI", index, 0)[1] >= 16
                   for index in indexes)

    def land(state: _State, mapper: Callable) -> dict[str, DecodedTopic]:
        if only and only <= set(state.keep):
            batch.chunks = [chunk for chunk in batch.chunks if wanted(chunk[2])]
            if not batch.chunks:
                batch.size = 0
                return {}
        flight = _launch(state, batch, mapper, overlap=False)
        counts: dict[int, int] = {}
        for chunk_indexes in flight.indexes:
            for index in chunk_indexes:
                channel_id, length = struct.unpack_from("<HI", index, 0)
                counts[channel_id] = counts.get(channel_id, 0) + length // 16
        for channel_id, topic in state.keep.items():  # fresh columns, sized for this batch
            state.keep[channel_id] = state.found[topic.channel.topic] = DecodedTopic(topic.schema, topic.channel, counts.get(channel_id, 0))
        # channels defined in this batch are sized from it too, not from the whole file
        whole = state.counts, state.chunk_bytes
        state.counts, state.chunk_bytes = counts, int(flight.bases[-1])
        _land(state, flight)
        state.counts, state.chunk_bytes = whole
        decoded = {}
        for topic in state.keep.values():
            topic.finish()
            if topic.count:
                decoded[topic.channel.topic] = topic
        return decoded

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
                    yield land(state, mapper)
                if opcode == Opcode.CHUNK:
                    batch.add(offset, body)
                elif opcode == Opcode.SCHEMA:
                    state.schema(body)
                elif opcode == Opcode.CHANNEL:
                    state.channel(body)
                elif opcode == Opcode.MESSAGE:
                    raise Unsupported("messages outside chunks")
            if batch.chunks:
                yield land(state, mapper)
    except (InputError, struct.error, ValueError) as exc:
        raise Unsupported(f"damaged MCAP ({exc})") from None
    for channel_id, topic in state.keep.items():
        state.found[topic.channel.topic] = DecodedTopic(topic.schema, topic.channel, state.counts.get(channel_id, 0))
    return state.found
