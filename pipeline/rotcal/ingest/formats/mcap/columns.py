"""MCAP messages of fixed layout into columns, without a Python call per
message: ``mcap_fast`` hands over each kept channel's messages in a
decompressed chunk, and their fields become columns by strided views
or gathers (``fields``), each value copied once:

- ``sensor_msgs/msg/Imu`` in CDR whose ``frame_id`` keeps one length within
  a chunk (``ros2_cdr.imu_layout``);
- ``sensor_msgs/msg/JointState`` in CDR whose joint count and name lengths
  keep one layout within a chunk (``ros2_cdr.joint_layout``);
- JSON messages, one object each, parsed together as JSON lines by polars
  with the fields' types given.

Any other layout raises ``Unsupported``: the caller reads the file with the
per-message path instead.
"""

from __future__ import annotations

import struct
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import polars as pl
from mcap.records import Channel, Schema

from rotcal.ingest.formats.mcap.json_lines import json_lines, parse_json_lines
from rotcal.ingest.formats.mcap.records import Unsupported
from rotcal.ingest.formats.mcap.ros2_cdr import CDR_LE, imu_layout, joint_layout
from rotcal.ingest.formats.mcap.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA

MESSAGE_HEADER = 31  # opcode u8, length u64, channel u16, sequence u32, log time u64, publish time u64
_CDR_LE = int(np.frombuffer(CDR_LE, "<u4")[0])


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

    @property
    def count(self) -> int:
        return len(self.frame) if self.frame is not None else self._filled

    @property
    def parsed(self) -> pl.DataFrame:
        """A JSON channel's messages as parsed (the reader sets ``frame`` for every JSON channel)."""
        if self.frame is None:
            raise ValueError(f"channel {self.channel.topic!r} holds no parsed JSON messages")
        return self.frame

    @property
    def kind(self) -> str:
        if self.channel.message_encoding == "json":
            return "json"
        if self.channel.message_encoding == "cdr" and self.schema is not None:
            return {IMU_SCHEMA: "imu", JOINT_SCHEMA: "joint"}.get(self.schema.name, "other")
        return "other"

    def add(self, k: int, layout: Layout, values: Callable[[], dict[str, np.ndarray]]) -> Callable[[], None]:
        """Reserve one chunk's ``k`` rows in the channel's arrays (of
        ``layout``), allocated once for all its messages (counted from the
        message indexes), so no column is ever held twice; returns the
        checking and copying of the chunk's ``values`` into them, which may
        run after later chunks' ``add`` (chunks are added in file order, then
        checked and copied side by side on the pool's threads)."""
        if not self.columns:
            self.columns = _columns(self.capacity, layout)
        start = self._filled
        if {name: (c.dtype, c.shape[1:]) for name, c in self.columns.items()} != layout:
            raise Unsupported("message layout changes between chunks")
        if start + k > len(self.columns["t_ns"]):
            raise Unsupported("more messages than the message indexes count")
        self._filled += k
        columns = self.columns

        def copy() -> None:
            for name, column in values().items():
                columns[name][start : start + k] = column
        return copy

    def add_json(self, log_ns: np.ndarray, lines: tuple[bytes, int]) -> None:
        """Keep one chunk's JSON messages (``json_lines``: one a line, and
        their colons), parsed together at ``finish``."""
        self._parts.append((log_ns, lines))

    def finish(self) -> None:
        if self.kind == "json":
            parts, self._parts = self._parts, []
            log_ns = np.concatenate([p[0] for p in parts]) if parts else np.zeros(0, np.int64)
            self.frame = parse_json_lines([p[1][0] for p in parts], log_ns.size, sum(p[1][1] for p in parts))
            self.columns = {"log_ns": log_ns}
            return
        self.columns = {name: column[: self._filled] for name, column in self.columns.items()} or {"t_ns": np.zeros(0, np.int64)}

    def take(self) -> dict[str, np.ndarray]:
        """The columns, handed over: the topic keeps no reference to them."""
        columns, self.columns = self.columns, {}
        return columns


Layout = dict[str, tuple[np.dtype, tuple[int, ...]]]  # each column's type and the shape of its rows


def _columns(rows: int, layout: Layout) -> dict[str, np.ndarray]:
    """Columns of ``rows`` rows of ``layout``, carved out of one
    block: over 4 MiB numpy asks the kernel for huge pages, so filling them
    costs a few page faults where columns of their own took a fault every
    4 KiB (most of the copying's time on the bench capture)."""
    sizes = [rows * dtype.itemsize * int(np.prod(shape)) for dtype, shape in layout.values()]
    starts = np.cumsum([0, *(-(-size // 64) * 64 for size in sizes)])  # each column on a cache line of its own
    block = np.empty(int(starts[-1]), np.uint8)
    return {name: block[start : start + size].view(dtype).reshape((rows, *shape))
            for (name, (dtype, shape)), start, size in zip(layout.items(), starts.tolist(), sizes)}


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
        return Records(self.raw, self.starts, self.step, self.skip + MESSAGE_HEADER, self.uniform)

    def first(self, size: int) -> bytes:
        """The first record's ``size`` bytes (from ``skip``)."""
        start = int(self.starts[0]) + self.skip
        return self.raw[start : start + size].tobytes()


_DTYPES: dict[str, np.dtype] = {}  # by their names: np.dtype("<u4") costs more than the view it describes


def fields(records: Records, offset: int, dtype: str, count: int = 1) -> np.ndarray:
    """``count`` values of ``dtype`` at byte ``offset`` of each record, as an
    (n,) or (n, count) array: a strided view of the chunk where the records
    are evenly spaced (a channel's run of messages of one size), else gathered
    through a view with a row at every byte; no record is copied whole, so
    each value is copied once, into its column (``DecodedTopic.add``)."""
    kind, raw, starts = _DTYPES.get(dtype) or _DTYPES.setdefault(dtype, np.dtype(dtype)), records.raw, records.starts
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
    return t_ns if t_ns.all() else np.where(t_ns == 0, log_ns, t_ns)  # stamps are rarely zero: one reduction, no mask


def _check_cdr(data: Records) -> None:
    if (fields(data, 0, "<u4") != _CDR_LE).any():
        raise Unsupported("CDR messages in another byte order")


_STAMP = np.dtype(np.int64)
_IMU_LAYOUT: Layout = {"t_ns": (_STAMP, ()), "x": (np.dtype("<f8"), ()), "y": (np.dtype("<f8"), ()), "z": (np.dtype("<f8"), ())}


def _decode_imu(data: Records, size: int, log_ns: np.ndarray) -> tuple[Layout, Callable[[], dict[str, np.ndarray]]]:
    """Imu messages of one ``size`` (``data``: their data): the columns'
    layout (from the first message) and their values, checked, when asked."""
    if size < 16:  # the encapsulation, the stamp and the frame_id length
        raise Unsupported("Imu message shorter than its header")
    lay = imu_layout(int.from_bytes(data.first(16)[12:], "little"))
    if size != lay.size:
        raise Unsupported("Imu frame_id of varying length")

    def values() -> dict[str, np.ndarray]:
        _check_cdr(data)
        if (fields(data, 12, "<u4") != lay.frame_id_len).any():
            raise Unsupported("Imu frame_id of varying length")
        acc = fields(data, lay.linear_acceleration, "<f8", 3)
        return {"t_ns": _stamp_or_log(data, lay.stamp, log_ns), "x": acc[:, 0], "y": acc[:, 1], "z": acc[:, 2]}
    return _IMU_LAYOUT, values


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


def _decode_joint(data: Records, size: int, log_ns: np.ndarray) -> tuple[Layout, Callable[[], dict[str, np.ndarray]]]:
    """JointState messages of one ``size`` (``data``: their data): the
    columns' layout (from the first message) and their values, checked, when asked."""
    try:
        shape = _joint_shape(data.first(size))
    except struct.error:
        raise Unsupported("JointState message shorter than its fields") from None
    lay = joint_layout(*shape)
    if size != lay.size:
        raise Unsupported("JointState messages of varying layout")
    n_joints, n_vel = len(lay.names), shape[2]
    layout: Layout = {"t_ns": (_STAMP, ()), "name": (np.dtype(f"S{max(lay.name_lens) - 1}"), (n_joints,)),
                      "position": (np.dtype("<f8"), (n_joints,)), "velocity": (np.dtype("<f8"), (n_vel,))}

    def values() -> dict[str, np.ndarray]:
        _check_cdr(data)
        if any((fields(data, o, "<u4") != v).any() for o, v in lay.counts):
            raise Unsupported("JointState messages of varying layout")
        names = np.column_stack([fields(data, o, f"S{k - 1}") for o, k in zip(lay.names, lay.name_lens)])
        position = fields(data, lay.position, "<f8", n_joints).reshape(data.count, -1)
        velocity = fields(data, lay.velocity, "<f8", n_vel).reshape(data.count, n_vel)
        return {"t_ns": _stamp_or_log(data, lay.stamp, log_ns), "name": names, "position": position, "velocity": velocity}
    return layout, values


def _message_sizes(records: Records, channel_id: int, kind: str) -> np.ndarray:
    """Each message's data size, checked: records of ``channel_id``, of one
    size unless JSON (of a uniform run of CDR messages, the one size only)."""
    if records.uniform:  # one size: CDR reads the first only
        return np.full(records.count if kind == "json" else 1, records.step - MESSAGE_HEADER)
    sizes = fields(records, 1, "<u8").astype(np.int64) - (MESSAGE_HEADER - 9)
    if np.any(sizes < 0):
        raise Unsupported("message record shorter than its header")
    if kind != "json" and np.any(sizes != sizes[0]):
        raise Unsupported("CDR messages of varying size")
    if np.any(fields(records, 9, "<u2") != channel_id):
        raise Unsupported("message index of another channel")
    return sizes


def decode_messages(topic: DecodedTopic, records: Records, channel_id: int, chunk_bytes: int) -> Callable[[], None]:
    """Add one channel's message ``records`` in a decompressed chunk (each a
    complete record, by ``mcap_fast``) to ``topic``; the chunks of the file
    expand to ``chunk_bytes``. Returns the copy into the columns still to
    make (``DecodedTopic.add``)."""
    sizes = _message_sizes(records, channel_id, topic.kind)
    # message indexes can claim any number of messages; the chunks hold no more than this many of this size
    topic.capacity = min(topic.capacity, chunk_bytes // (int(sizes[0]) + MESSAGE_HEADER))
    log_ns = fields(records, 15, "<i8")
    if topic.kind == "json":
        topic.add_json(log_ns.copy(), json_lines(records.raw, records.starts + MESSAGE_HEADER, sizes))
        return _nothing
    decode = _decode_imu if topic.kind == "imu" else _decode_joint
    return topic.add(records.count, *decode(records.data(), int(sizes[0]), log_ns))


def _nothing() -> None:
    """No copy left to make."""
