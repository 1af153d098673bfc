"""MCAP records without a Python call per message.

A chunk is decompressed once, by one thread of a pool, into that thread's
buffer; its message index records (which every indexed MCAP writer puts
after each chunk) give each channel's message offsets, so the records are
located with array arithmetic and checked to tile the chunk exactly (a run
of one channel's messages of one size, back to back, with two strided reads
a message); the few other records in a chunk (schemas, channels) are read
one by one in the gaps, in file order. The messages of the kept channels
become columns in ``mcap_columns``, decoded by the same thread.

Records are read by ``mcap_records``, as the per-message path reads them
(declared sizes checked, CRCs checked). Anything else (no message index or
one that declares more than it holds, messages outside chunks, other
layouts, damaged files) raises ``Unsupported``: the caller then reads the
file with the per-message path, which is also the one that words every
error, so both paths give the same samples and the same messages.
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Callable, Generator, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, nullcontext
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import BinaryIO

import numpy as np
from mcap.opcode import Opcode
from mcap.records import Schema

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap.chunks import tiles
from rotcal.ingest.formats.mcap.columns import DecodedTopic, Records, decode_messages
from rotcal.ingest.formats.mcap.records import McapFile, Unsupported, chunk_data, chunk_records, parse_channel, parse_schema, top_records
from rotcal.ingest.formats.mcap.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.parallel import cores

# Chunks are read and handed to the thread pool together up to this many
# bytes, compressed and decompressed, counted from their declared sizes, in
# two batches (one read while the other is decompressed and decoded); a batch
# holds one chunk at least (at most the record limit). Each thread
# decompresses into one buffer of its own, reused from chunk to chunk (no
# page faults, and the chunk is still in its cache when it is decoded); a
# batch of a chunk above half this is done in the reading thread alone.
BATCH_BYTES = 32 * 1024 * 1024


def _done_event() -> threading.Event:
    event = threading.Event()
    event.set()
    return event


@dataclass
class _State:
    where: McapFile
    topics: set[str]
    counts: dict[int, int]
    chunk_bytes: int
    # each thread's buffer for the chunk it decompresses and decodes
    buffers: dict[int, np.ndarray] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    found: dict[str, DecodedTopic] = field(default_factory=dict)
    keep: dict[int, DecodedTopic] = field(default_factory=dict)
    # the last chunk launched, decoded once this is set (chunks are decoded in file order)
    last: threading.Event = field(default_factory=lambda: _done_event())
    # every chunk's event, set when the read ends whatever became of the chunk
    launched: list[threading.Event] = field(default_factory=list)
    failed: bool = False

    def release(self, failed: bool) -> None:
        """Set every chunk's event as the read ends: a chunk whose job raised, was cancelled (a pool's map
        cancels the rest of its batch when one raises) or never ran (a batch run in this thread stops at its
        first failure) leaves later chunks waiting on it; they then see the read failed and skip decoding."""
        self.failed = self.failed or failed
        for event in self.launched:
            event.set()

    def buffer(self, size: int) -> np.ndarray:
        """This thread's buffer, ``size`` bytes of it."""
        own = self.buffers.get(threading.get_ident(), np.empty(0, np.uint8))
        if own.size < size:
            own = self.buffers[threading.get_ident()] = np.empty(size, np.uint8)
        return own[:size]

    def schema(self, body: bytes | memoryview) -> None:
        record = parse_schema(body, self.where)
        self.schemas[record.id] = record

    def channel(self, body: bytes | memoryview) -> int | None:
        """Register a channel as the per-message path does; returns its id if its messages are to be
        decoded. A second channel of a decoded topic is left to the per-message path (it reads them all)."""
        record = parse_channel(body, self.where)
        if record.topic in self.found:
            first = self.found[record.topic].channel.id
            if record.id != first and first in self.keep:  # (a writer may repeat a channel's record per chunk)
                raise Unsupported("a topic over several channels")  # the per-message path reads them all
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


@dataclass
class _Job:
    """One chunk of a batch, decoded once the chunk before it is
    (``previous`` set), which then sets ``decoded``."""

    chunk: tuple[int, bytes, list[bytes]]
    previous: threading.Event
    decoded: threading.Event = field(default_factory=threading.Event)


def _inflate(state: _State, job: _Job) -> None:
    """One chunk, on a pool thread: decompressed into the thread's buffer,
    CRC-checked and its records located (side by side with the other
    threads: zstd, crc32 and numpy's copies release the GIL), then decoded
    in file order (the schemas and channels a chunk defines apply to the
    chunks after it; its rows in the columns are reserved), then its values
    copied into their rows, side by side with the next chunk's decoding. A
    failure anywhere marks the read failed: later chunks skip their decoding."""
    try:
        offset, body, indexes = job.chunk
        raw = state.buffer(_declared(body))
        chunk_data(body, offset, state.where, raw.data)
        by_channel, gaps = tiles(raw, indexes)
        job.previous.wait()
        copies = [] if state.failed else _decode(state, raw, by_channel, gaps)
        job.decoded.set()  # the next chunk may be decoded while this one's columns are copied
        for copy in copies:
            copy()
    except BaseException:
        state.failed = True
        raise
    finally:
        job.decoded.set()


@dataclass
class _Flight:
    """A batch whose chunks are being decompressed and decoded: ``done``
    yields as each one is."""

    done: Iterator
    size: int


def _launch(state: _State, batch: _Batch, mapper: Callable) -> _Flight:
    """Start decompressing and decoding a batch with ``mapper`` (a thread
    pool's map, which submits every chunk at once), or in this thread (as
    it is landed) when a chunk is larger than half ``BATCH_BYTES``."""
    largest = max(_declared(body) for _, body, _ in batch.chunks)
    if largest > state.where.limits.max_mcap_record_bytes:
        raise Unsupported("a chunk declares more than the record limit")  # the per-message path says so
    jobs = []
    for chunk in batch.chunks:
        jobs.append(_Job(chunk, state.last))
        state.last = jobs[-1].decoded
        state.launched.append(state.last)
    size, batch.chunks, batch.size = batch.size, [], 0
    return _Flight((map if largest > BATCH_BYTES // 2 else mapper)(partial(_inflate, state), jobs), size)


def _relay(state: _State, batch: _Batch, mapper: Callable, flight: _Flight | None) -> _Flight:
    """Launch ``batch`` while the one in ``flight`` finishes, when both fit
    in ``BATCH_BYTES`` (else one after the other)."""
    if flight is not None and flight.size + batch.size > BATCH_BYTES:
        _land(flight)
        flight = None
    launched = _launch(state, batch, mapper)
    _land(flight)
    return launched


def _land(flight: _Flight | None) -> None:
    """Wait for a batch's chunks to be decoded (raising what any raised)."""
    if flight is not None:
        for _ in flight.done:
            pass


def _decode(state: _State, raw: np.ndarray, by_channel: dict[int, Records], gaps: list[tuple[int, int]]) -> list[Callable[[], None]]:
    """Read the records in a chunk's ``gaps`` (schemas, channels) and decode
    the messages of the kept channels, their rows in the columns reserved;
    returns the copies into them still to make."""
    defined_at = {}
    view = raw.data
    for lo, hi in gaps:
        for opcode, pos, record in chunk_records(view[lo:hi], 0, state.where):
            if opcode == Opcode.MESSAGE:
                raise Unsupported("chunk record outside the message index")
            if opcode == Opcode.SCHEMA:
                state.schema(record)
            elif opcode == Opcode.CHANNEL and (cid := state.channel(record)) is not None:
                defined_at[cid] = lo + pos
    copies = []
    for channel_id, records in by_channel.items():
        topic = state.keep.get(channel_id)
        if topic is None or records.count == 0:
            continue  # the per-message path skips messages of channels it has not kept (yet)
        if records.starts[0] < defined_at.get(channel_id, -1):
            raise Unsupported("messages before their channel record")
        copies.append(decode_messages(topic, records, channel_id, state.chunk_bytes))
    return copies


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


@contextmanager
def _reading(path: Path, where: McapFile, topics: set[str], workers: int) -> Iterator[tuple[BinaryIO, Callable, _State]]:
    """The open file, the map that decompresses and decodes chunks (a pool
    of ``parallel.cores(workers)`` threads, or this thread for one), and the
    state of the read, sized from the message index records.

    Free of deadlock at any thread count: a pool thread blocks only until the chunk before its own is
    decoded, and that chunk was launched before it (on the pool, whose queue is first in, first out, or in
    this thread, landed first); should the read end early (a damaged or unsupported chunk, an interrupt),
    every chunk's event is set (``_State.release``) before the pool is joined."""
    threads = cores(workers)
    with path.open("rb") as fh, ThreadPoolExecutor(threads) if threads > 1 else nullcontext() as pool:
        state = _State(where, topics, *_message_counts(fh, where))
        try:
            yield fh, map if pool is None else pool.map, state
        except BaseException:
            state.release(failed=True)
            raise
        state.release(failed=False)


def _handovers(fh, state: _State, batch: _Batch) -> Iterator[bool]:
    """Walk the file's top-level records, filling ``batch`` with chunks and
    their message indexes, and registering schemas and channels outside
    chunks. Yields when the batch is to be handed over: False when it is
    full, True when a record outside chunks follows (or the file ends), so
    that every chunk handed over before it must be decoded first."""
    for opcode, offset, length in top_records(fh, state.where):
        if opcode == Opcode.MESSAGE_INDEX and batch.chunks:
            batch.chunks[-1][2].append(fh.read(length))
            continue
        body = fh.read(length) if opcode in (Opcode.CHUNK, Opcode.SCHEMA, Opcode.CHANNEL) else b""
        if opcode == Opcode.CHUNK and batch.fits(body):
            batch.add(offset, body)
            continue
        if batch.chunks or opcode != Opcode.CHUNK:
            yield opcode != Opcode.CHUNK
        if opcode == Opcode.CHUNK:
            batch.add(offset, body)
        elif opcode == Opcode.SCHEMA:
            state.schema(body)
        elif opcode == Opcode.CHANNEL:
            state.channel(body)
        elif opcode == Opcode.MESSAGE:
            raise Unsupported("messages outside chunks")
    yield True


def read_topics(path: Path, topics: set[str], limits: Limits, workers: int = 0) -> dict[str, DecodedTopic]:
    """Every channel by topic, with the messages of ``topics`` and of any Imu
    or JointState channel decoded into columns; chunks are decompressed and
    decoded on ``parallel.cores(workers)`` threads (one: in this thread, no
    pool), handed over at most ``BATCH_BYTES`` at a time while the next
    batch is read.

    Raises ``Unsupported`` for anything but a chunked, indexed file of
    layouts this module decodes, damaged files included (the per-message
    path words their errors).
    """
    batch, flight = _Batch(), None
    where = McapFile(path, limits)
    try:
        with _reading(path, where, topics, workers) as (fh, mapper, state):
            for barrier in _handovers(fh, state, batch):
                if batch.chunks:
                    flight = _relay(state, batch, mapper, flight)
                if barrier:
                    flight, landing = None, flight
                    _land(landing)
    except (InputError, struct.error, ValueError) as exc:
        raise Unsupported(f"damaged MCAP ({exc})") from None
    for topic in state.keep.values():
        topic.finish()
    return state.found


def iter_topic_batches(path: Path, topics: set[str], limits: Limits, workers: int = 0,
                       only: frozenset[int] = frozenset()) -> Generator[dict[str, DecodedTopic], None, dict[str, DecodedTopic]]:
    """``read_topics`` a batch of chunks at a time: after
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
        counts: dict[int, int] = {}
        for _, _, chunk_indexes in batch.chunks:
            for index in chunk_indexes:
                channel_id, length = struct.unpack_from("<HI", index, 0)
                counts[channel_id] = counts.get(channel_id, 0) + length // 16
        chunk_bytes = sum(_declared(body) for _, body, _ in batch.chunks)
        for channel_id, topic in state.keep.items():  # fresh columns, sized for this batch
            state.keep[channel_id] = state.found[topic.channel.topic] = DecodedTopic(topic.schema, topic.channel, counts.get(channel_id, 0))
        # channels defined in this batch are sized from it too, not from the whole file
        whole = state.counts, state.chunk_bytes
        state.counts, state.chunk_bytes = counts, chunk_bytes
        _land(_launch(state, batch, mapper))
        state.counts, state.chunk_bytes = whole
        decoded = {}
        for topic in state.keep.values():
            topic.finish()
            if topic.count:
                decoded[topic.channel.topic] = topic
        return decoded

    try:
        with _reading(path, where, topics, workers) as (fh, mapper, state):
            for _ in _handovers(fh, state, batch):
                if batch.chunks:
                    yield land(state, mapper)
    except (InputError, struct.error, ValueError) as exc:
        raise Unsupported(f"damaged MCAP ({exc})") from None
    for channel_id, topic in state.keep.items():
        state.found[topic.channel.topic] = DecodedTopic(topic.schema, topic.channel, state.counts.get(channel_id, 0))
    return state.found
