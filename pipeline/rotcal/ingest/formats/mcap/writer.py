"""Write captures as MCAP: the DUT as ``sensor_msgs/msg/Imu`` (CDR) or JSON
messages, the table as ``sensor_msgs/msg/JointState`` (CDR) or JSON
(docs/inputs.md, "MCAP captures"). Used by the simulator and ``rotcal apply``;
zstd-compressed chunks.

CDR captures are written a chunk at a time: the messages have fixed layouts
(``ros2_cdr``), so a chunk's records are one structured numpy array, and the
file is byte for byte what ``mcap_ros2.writer.Writer`` writes with its
defaults for the same messages (tested), without a Python call per message.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import BinaryIO

import mcap_ros2
import numpy as np
import polars as pl
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Channel, Chunk, ChunkIndex, DataEnd, Footer, Header, McapRecord, Schema, Statistics, SummaryOffset
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from rotcal.ingest.formats.mcap import ros2_cdr, ros2_msgdefs
from rotcal.model.physics import AXES, JOINT_SIGN
from rotcal.tables import atomic_write

MAGIC = b"\x89MCAP0\r\n"
CHUNK_BYTES = 1024 * 1024  # mcap's default chunk size
ROS2_LIBRARY = f"{LIBRARY_IDENTIFIER} mcap-ros2-support/{mcap_ros2.__version__}"
_MESSAGE_HEADER = 31  # opcode, length, channel id, sequence, log time, publish time


def _record_bytes(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


class ChunkedWriter:
    """An MCAP writer for blocks of fixed-layout messages.

    Same records, chunking rule (a chunk closes once it passes
    ``chunk_bytes``), indexes, statistics and summary as ``mcap.writer.Writer``
    with its defaults and zstd; messages are added as a block of one channel
    sharing one layout, each message given as a byte template and the
    per-message fields written into it.
    """

    def __init__(self, fh: BinaryIO, profile: str, library: str, chunk_bytes: int = CHUNK_BYTES):
        self._fh = fh
        self._chunk_bytes = chunk_bytes
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._chunk_indexes: list[ChunkIndex] = []
        self._counts: dict[int, int] = {}
        self._span: tuple[int, int] | None = None
        self._reset_chunk()
        fh.write(MAGIC)
        fh.write(_record_bytes(Header(profile, library)))

    def _reset_chunk(self) -> None:
        self._pieces: list[bytes] = []
        self._size = 0
        self._index: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}

    def _append(self, data: bytes) -> None:
        self._pieces.append(data)
        self._size += len(data)

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._append(_record_bytes(schema))
        self._maybe_close_chunk()
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
                          schema_id=schema_id, metadata={})
        self._channels.append(channel)
        self._append(_record_bytes(channel))
        self._maybe_close_chunk()
        return channel.id

    def add_messages(self, channel_id: int, log_ns: np.ndarray, template: np.ndarray,
                     fields: list[tuple[int, np.ndarray]]) -> None:
        """Messages on ``channel_id`` logged (and published) at ``log_ns``:
        each is ``template`` with ``fields[k][1][i]``'s bytes at offset
        ``fields[k][0]``."""
        log_ns = np.asarray(log_ns, np.int64)
        record = np.dtype([("op", "u1"), ("length", "<u8"), ("channel", "<u2"), ("sequence", "<u4"),
                           ("log", "<u8"), ("publish", "<u8"), ("data", "u1", (template.size,))])
        start = 0
        while start < log_ns.size:
            fit = max(1, (self._chunk_bytes - self._size) // record.itemsize + 1)  # the one that passes the limit closes it
            stop = min(start + fit, log_ns.size)
            part = slice(start, stop)
            block = np.zeros(stop - start, record)
            block["op"] = Opcode.MESSAGE
            block["length"] = record.itemsize - 9
            block["channel"] = channel_id
            block["log"] = block["publish"] = log_ns[part]
            data = block["data"]
            data[:] = template
            for offset, values in fields:
                raw = np.ascontiguousarray(values[part])
                data[:, offset : offset + raw.itemsize] = raw.view(np.uint8).reshape(raw.size, raw.itemsize)
            offsets = self._size + record.itemsize * np.arange(stop - start, dtype=np.uint64)
            self._index.setdefault(channel_id, []).append((log_ns[part], offsets))
            self._append(block.tobytes())
            self._counts[channel_id] = self._counts.get(channel_id, 0) + stop - start
            first, last = int(log_ns[part].min()), int(log_ns[part].max())
            self._span = (first, last) if self._span is None else (min(self._span[0], first), max(self._span[1], last))
            start = stop
            self._maybe_close_chunk()

    def _maybe_close_chunk(self) -> None:
        if self._index and self._size > self._chunk_bytes:
            self._close_chunk()

    def _close_chunk(self) -> None:
        if not self._index:
            return
        raw = b"".join(self._pieces)
        logs = np.concatenate([t for parts in self._index.values() for t, _ in parts])
        compressed = zstandard.compress(raw)
        chunk = Chunk(compression="zstd", data=compressed, message_start_time=int(logs.min()),
                      message_end_time=int(logs.max()), uncompressed_crc=zlib.crc32(raw), uncompressed_size=len(raw))
        chunk_start = self._fh.tell()
        chunk_bytes = _record_bytes(chunk)
        self._fh.write(chunk_bytes)
        index_start = self._fh.tell()
        index_offsets, written = {}, 0
        for channel_id, parts in self._index.items():
            pairs = np.empty((sum(t.size for t, _ in parts), 2), "<u8")
            pairs[:, 0] = np.concatenate([t for t, _ in parts])
            pairs[:, 1] = np.concatenate([o for _, o in parts])
            body = struct.pack("<HI", channel_id, pairs.nbytes) + pairs.tobytes()
            index_offsets[channel_id] = index_start + written
            self._fh.write(struct.pack("<BQ", Opcode.MESSAGE_INDEX, len(body)) + body)
            written += 9 + len(body)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=chunk.message_start_time, message_end_time=chunk.message_end_time,
            chunk_start_offset=chunk_start, chunk_length=len(chunk_bytes), message_index_offsets=index_offsets,
            message_index_length=written, compression="zstd", compressed_size=len(compressed),
            uncompressed_size=len(raw),
        ))
        self._reset_chunk()

    def finish(self) -> None:
        """Close the last chunk; write the summary (schemas, channels,
        statistics, chunk index, empty attachment and metadata indexes), the
        summary offsets and the footer."""
        self._close_chunk()
        self._fh.write(_record_bytes(DataEnd(0)))
        summary_start = self._fh.tell()
        start, end = self._span or (0, 0)
        stats = Statistics(
            message_count=sum(self._counts.values()), schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=0, metadata_count=0,
            chunk_count=len(self._chunk_indexes), message_start_time=start, message_end_time=end,
            channel_message_counts=dict(self._counts),
        )
        groups: list[tuple[int, list]] = [(Opcode.SCHEMA, self._schemas), (Opcode.CHANNEL, self._channels), (Opcode.STATISTICS, [stats]),
                  (Opcode.CHUNK_INDEX, self._chunk_indexes), (Opcode.ATTACHMENT_INDEX, []),
                  (Opcode.METADATA_INDEX, [])]
        summary, offsets = b"", []
        for opcode, records in groups:
            data = b"".join(_record_bytes(r) for r in records)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + len(summary),
                                         group_length=len(data)))
            summary += data
        offset_start = summary_start + len(summary)
        summary += b"".join(_record_bytes(o) for o in offsets)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, offset_start), zlib.crc32(summary))
        self._fh.write(summary)
        self._fh.write(_record_bytes(Footer(summary_start=summary_start, summary_offset_start=offset_start,
                                            summary_crc=crc)))
        self._fh.write(MAGIC)


def register_imu_schema(writer: ChunkedWriter) -> int:
    """The ``sensor_msgs/msg/Imu`` schema (ROS 2 message definition)."""
    return writer.register_schema("sensor_msgs/msg/Imu", "ros2msg", ros2_msgdefs.IMU.encode())


def imu_channel(writer: ChunkedWriter, schema_id: int, topic: str, frame_id: str) -> Callable[..., None]:
    """A channel of Imu messages; returns the function that adds a block of
    them, stamped (and logged) at ``t_ns``: the three ``linear_acceleration``
    columns (x, y, z) and, when given, the nine row-major elements of
    ``linear_acceleration_covariance`` (all zeros otherwise: "covariance
    unknown"); orientation and angular velocity marked not provided
    (``ros2_cdr.imu_template``). Blocks added one after another give the
    bytes one call with all of them would (the writer's chunks do not see
    the block boundaries)."""
    template = ros2_cdr.imu_template(frame_id)
    lay = ros2_cdr.imu_layout(len(frame_id.encode()) + 1)
    channel = writer.register_channel(topic, "cdr", schema_id)
    acc_cov = lay.linear_acceleration + 24  # the covariance follows the vector's three float64s

    def add(t_ns: np.ndarray, acceleration: Sequence[np.ndarray], covariance: Sequence[np.ndarray] = ()) -> None:
        fields = [(lay.linear_acceleration + 8 * k, np.asarray(a, "<f8")) for k, a in enumerate(acceleration)]
        fields += [(acc_cov + 8 * k, np.asarray(c, "<f8")) for k, c in enumerate(covariance)]
        writer.add_messages(channel, t_ns, template, [*_stamp_fields(lay.stamp, t_ns), *fields])

    return add


def add_imu_messages(writer: ChunkedWriter, schema_id: int, topic: str, frame_id: str, t_ns: np.ndarray,
                     acceleration: Sequence[np.ndarray], covariance: Sequence[np.ndarray] = ()) -> None:
    """A channel of Imu messages in one block (``imu_channel``)."""
    imu_channel(writer, schema_id, topic, frame_id)(t_ns, acceleration, covariance)


def _write_cdr(fh: BinaryIO, blocks: Iterable[tuple[np.ndarray, list[np.ndarray]]], tables: Iterable[pl.DataFrame],
               imu_topic: str, table_topic: str) -> None:
    """Imu and JointState messages in the order ``mcap_ros2`` would be given
    them: the table's (from ``tables``, frames of t_ns, axis, rate_hz,
    angle_deg in time order), then the DUT's (from ``blocks`` of (t_ns, [u,
    v, w]) in time order; the reader sorts by time)."""
    writer = ChunkedWriter(fh, "ros2", ROS2_LIBRARY)
    imu_schema = register_imu_schema(writer)
    joint_schema = writer.register_schema("sensor_msgs/msg/JointState", "ros2msg", ros2_msgdefs.JOINT_STATE.encode())
    template, lay = ros2_cdr.joint_template("table", (2,), 1, 0)
    channel = None
    for table in tables:
        if not table.height:
            continue
        channel = channel or writer.register_channel(table_topic, "cdr", joint_schema)
        t_ns = table["t_ns"].to_numpy()
        axis = table["axis"].to_numpy()
        sign = np.select([axis == a for a in AXES], [JOINT_SIGN[a] for a in AXES])
        writer.add_messages(channel, t_ns, template, [
            *_stamp_fields(lay.stamp, t_ns),
            (lay.names[0], np.array([a.encode() for a in axis], "S1")),
            (lay.position, sign * np.deg2rad(table["angle_deg"].to_numpy())),
            (lay.velocity, sign * 2 * np.pi * table["rate_hz"].to_numpy()),
        ])
    add = None
    for t_ns, acceleration in blocks:
        add = add or imu_channel(writer, imu_schema, imu_topic, "dut")
        add(t_ns, acceleration)
    writer.finish()


def _stamp_fields(offset: int, t_ns: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """builtin_interfaces/Time: int32 seconds and uint32 nanoseconds."""
    sec, nanosec = np.divmod(t_ns, 1_000_000_000)
    return [(offset, sec.astype("<i4")), (offset + 4, nanosec.astype("<u4"))]


def _write_json(writer: Writer, samples: pl.DataFrame, table: pl.DataFrame, imu_topic: str, table_topic: str) -> None:
    writer.start(profile="", library="rotcal")
    schema = writer.register_schema("rotcal/Sample", "jsonschema", json.dumps({"type": "object"}).encode())
    table_schema = writer.register_schema("rotcal/Table", "jsonschema", json.dumps({"type": "object"}).encode())
    imu = writer.register_channel(imu_topic, "json", schema)
    tab = writer.register_channel(table_topic, "json", table_schema)
    for t_ns, axis, rate, angle in table.iter_rows():
        body = {"t": t_ns / 1e9, "axis": axis, "rate_hz": rate, "angle_deg": angle}
        writer.add_message(tab, t_ns, json.dumps(body).encode(), t_ns)
    for t_ns, u, v, w in samples.select("t_ns", "u", "v", "w").iter_rows():
        writer.add_message(imu, t_ns, json.dumps({"t": t_ns / 1e9, "u": u, "v": v, "w": w}).encode(), t_ns)
    writer.finish()


def write_capture(samples: pl.DataFrame, table: pl.DataFrame, path: Path, encoding: str,
                  imu_topic: str = "/imu", table_topic: str = "/table/joint_states") -> Path:
    """Write ``samples`` (t_ns, u, v, w) and ``table`` (t_ns, axis, rate_hz,
    angle_deg) to ``path``, atomically."""
    if encoding == "cdr":
        blocks = [(samples["t_ns"].to_numpy(), [samples[c].cast(pl.Float64).to_numpy() for c in "uvw"])]
        return write_cdr_blocks(blocks if samples.height else [], [table], path, imu_topic, table_topic)

    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            _write_json(Writer(fh, compression=CompressionType.ZSTD), samples, table, imu_topic, table_topic)

    atomic_write(path, write)
    return path


def write_cdr_blocks(blocks: Iterable[tuple[np.ndarray, list[np.ndarray]]], tables: Iterable[pl.DataFrame], path: Path,
                     imu_topic: str = "/imu", table_topic: str = "/table/joint_states") -> Path:
    """A CDR capture written as ``write_capture`` writes it, the table's
    messages a frame at a time and the DUT's samples a block at a time (t_ns,
    [u, v, w]): the file's bytes are the same, and only one block is in
    memory at once."""
    def write(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            _write_cdr(fh, blocks, tables, imu_topic, table_topic)

    atomic_write(path, write)
    return path


def write_samples(samples: pl.DataFrame, path: Path, table: pl.DataFrame | None = None, encoding: str = "cdr") -> Path:
    """The registry's writer (``ingest.formats``): ``samples`` as one MCAP
    capture, with the table's messages ``table`` (t_ns, axis, rate_hz,
    angle_deg; none by default: an unlabelled capture)."""
    empty = pl.DataFrame(schema={"t_ns": pl.Int64, "axis": pl.String, "rate_hz": pl.Float64, "angle_deg": pl.Float64})
    return write_capture(samples, empty if table is None else table, path, encoding)
