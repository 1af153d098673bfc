"""MCAP captures: ``sensor_msgs/msg/Imu`` (CDR) or JSON messages on the DUT
topic, and an optional table channel (``sensor_msgs/msg/JointState`` or JSON)
whose labels are mapped onto the DUT's time stamps (contract sections 1, 2).

Files are decoded by ``mcap_fast`` (whole chunks into columns) where it knows
the layouts, else message by message here; both feed the same steps.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np
import polars as pl
import zstandard
from mcap.exceptions import McapError
from mcap.reader import StreamReader
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import breakup_chunk
from mcap_ros2.decoder import DecoderFactory

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError
from rotcal.ingest import mcap_fast
from rotcal.ingest.labels import label_columns, time_ordered
from rotcal.ingest.meta import CaptureSpec, DatasetMeta
from rotcal.model.physics import AXES, JOINT_SIGN

IMU_SCHEMA = "sensor_msgs/msg/Imu"
JOINT_SCHEMA = "sensor_msgs/msg/JointState"
JSON_FIELDS = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")


@dataclass(frozen=True)
class TableTrack:
    """Table-channel messages in time order: the commanded axis, rate and angle."""

    t_ns: np.ndarray
    axis: np.ndarray  # int8 index into AXES
    rate_hz: np.ndarray
    angle_deg: np.ndarray

    @cached_property
    def runs(self) -> tuple[np.ndarray, np.ndarray]:
        """Each message's run (same axis and rate) and the angle increment to
        the next message, unwrapped with the commanded rate (only sin and cos
        of theta are used, so no running sum is needed); computed once for
        all blocks of samples."""
        run_break = np.r_[True, (self.axis[1:] != self.axis[:-1]) | (self.rate_hz[1:] != self.rate_hz[:-1])]
        expected = 360.0 * self.rate_hz[:-1] * np.diff(self.t_ns) / 1e9
        increment = expected + (np.diff(self.angle_deg) - expected + 180.0) % 360.0 - 180.0
        return np.cumsum(run_break) - 1, increment


@dataclass
class _Topic:
    schema: Schema | None
    channel: Channel
    stamps: list
    rows: list

    @property
    def count(self) -> int:
        return len(self.rows)


def _chunk_records(chunk: Chunk, limit: int, path: Path) -> list:
    """A chunk's records, never decompressing more than ``limit`` bytes: a
    chunk of a few kilobytes can expand a million-fold, and the mcap library
    would allocate whatever its header claims."""
    if chunk.uncompressed_size > limit:
        raise LimitError(f"an MCAP chunk expands to {chunk.uncompressed_size} bytes, above the limit of {limit} bytes", path=path)
    try:
        data = mcap_fast.decompress_chunk(chunk.compression, chunk.data, chunk.uncompressed_size)
    except mcap_fast.Unsupported as exc:
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    return breakup_chunk(replace(chunk, compression="", data=data))


def _read_records(path: Path, topics: set[str], limits: Limits) -> dict[str, _Topic]:
    """Every channel by topic, with the raw messages of ``topics`` and of any
    Imu or JointState channel; refuses damaged files with the reason."""
    found: dict[str, _Topic] = {}
    schemas: dict[int, Schema] = {}
    keep: dict[int, _Topic] = {}
    try:
        with path.open("rb") as fh:
            limit = limits.max_mcap_record_bytes
            for record in (r for outer in StreamReader(fh, record_size_limit=limit, emit_chunks=True).records
                           for r in (_chunk_records(outer, limit, path) if isinstance(outer, Chunk) else [outer])):
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel) and record.topic not in found:
                    topic = _Topic(schemas.get(record.schema_id), record, [], [])
                    found[record.topic] = topic
                    kind = topic.schema.name if topic.schema is not None else ""
                    if record.topic in topics or kind in (IMU_SCHEMA, JOINT_SCHEMA):
                        keep[record.id] = topic
                elif isinstance(record, Message) and record.channel_id in keep:
                    topic = keep[record.channel_id]
                    topic.stamps.append(record.log_time)
                    topic.rows.append(record.data)
    except McapError as exc:
        if type(exc).__name__ == "RecordLengthLimitExceeded":
            raise LimitError(
                f"an MCAP record is larger than the limit of {limits.max_mcap_record_bytes} bytes", path=path
            ) from None
        if type(exc).__name__ == "EndOfFile":
            raise InputError("truncated MCAP: the file ends inside a record", path=path) from None
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    except (struct.error, ValueError, EOFError, OSError, zstandard.ZstdError, RuntimeError) as exc:
        raise InputError(f"corrupt MCAP: {exc}", path=path) from None
    return found


def _choose_topic(found: dict[str, _Topic], wanted: str, given: bool, schema_name: str, path: Path) -> str | None:
    """``wanted`` if present; else, when the topic was a default, the only
    channel of ``schema_name``; a topic named in dataset.toml must exist."""
    if wanted in found:
        return wanted
    if given:
        listing = ", ".join(sorted(found)) or "none"
        raise InputError(f"topic {wanted!r} is not in the file (topics: {listing})", path=path)
    typed = [t for t, v in found.items() if v.schema is not None and v.schema.name == schema_name]
    return typed[0] if len(typed) == 1 else None


def _decoder(topic: _Topic, path: Path):
    encoding = topic.channel.message_encoding
    if encoding == "json":
        return lambda data: json.loads(data)
    if encoding == "cdr" and topic.schema is not None:
        return DecoderFactory().decoder_for(encoding, topic.schema)
    raise InputError(
        f"topic {topic.channel.topic!r} has message encoding {encoding!r}; rotcal reads cdr and json", path=path
    )


def _imu_frame(topic: _Topic, path: Path) -> pl.DataFrame:
    decode = _decoder(topic, path)
    try:
        msgs = [decode(data) for data in topic.rows]
    except Exception as exc:  # a decoder failure is a corrupt message, whatever the library raises
        raise InputError(f"topic {topic.channel.topic!r}: message cannot be decoded ({exc})", path=path) from None
    log_ns = np.asarray(topic.stamps, np.int64)
    if topic.channel.message_encoding == "json":
        cols = {f: [m.get(f) for m in msgs] for f in JSON_FIELDS if any(f in m for m in msgs)}
        return _json_frame(pl.DataFrame(cols, strict=False), log_ns, topic.channel.topic, path)
    stamp = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for m in msgs], np.int64)
    return pl.DataFrame(
        {
            "t_ns": np.where(stamp == 0, log_ns, stamp),
            "u": [m.linear_acceleration.x for m in msgs],
            "v": [m.linear_acceleration.y for m in msgs],
            "w": [m.linear_acceleration.z for m in msgs],
        }
    )


def _json_frame(frame: pl.DataFrame, log_ns: np.ndarray, topic: str, path: Path) -> pl.DataFrame:
    """DUT samples from JSON fields: ``t`` (s) where given, else the log time."""
    missing = [f for f in ("u", "v", "w") if f not in frame.columns]
    if missing:
        raise InputError(f"topic {topic!r}: JSON messages lack {', '.join(missing)}", path=path)
    t_s = pl.col("t").cast(pl.Float64) if "t" in frame.columns else pl.lit(None, pl.Float64)
    stamp = (t_s * 1e9).round().cast(pl.Int64).fill_null(pl.Series(log_ns))
    return frame.with_columns(t_ns=stamp).drop("t", strict=False)


def _joint_axis(names: list[str], position: list[float], velocity: list[float], previous: tuple | None) -> int:
    """Index of the joint the table is working on: the only one, the fastest,
    or, with all at rest, the one that moved since the last message."""
    if len(names) == 1:
        return 0
    speed = np.abs(np.asarray(velocity if len(velocity) == len(names) else [0.0] * len(names)))
    if speed.max() > 0:
        return int(speed.argmax())
    if previous is not None:
        prev_names, prev_pos, prev_idx = previous
        moved = [i for i, n in enumerate(names) if n in prev_names and position[i] != prev_pos[prev_names.index(n)]]
        if moved:
            return moved[0]
        return prev_idx if prev_idx < len(names) else 0
    return 0


def _table_track(topic: _Topic, path: Path) -> TableTrack:
    decode = _decoder(topic, path)
    log_ns = np.asarray(topic.stamps, np.int64)
    t_ns, axis, rate, angle = [], [], [], []
    previous = None
    for data, log_t in zip(topic.rows, log_ns):
        try:
            m = decode(data)
        except Exception as exc:  # a decoder failure is a corrupt message, whatever the library raises
            raise InputError(f"table topic {topic.channel.topic!r}: message cannot be decoded ({exc})", path=path) from None
        if topic.channel.message_encoding == "json":
            t_ns.append(int(round(m["t"] * 1e9)) if "t" in m else int(log_t))
            axis.append(m.get("axis"))
            rate.append(float(m.get("rate_hz", np.nan)))
            angle.append(float(m.get("angle_deg", np.nan)))
            continue
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        names, pos, vel = list(m.name), list(m.position), list(m.velocity)
        i = _joint_axis(names, pos, vel, previous)
        previous = (names, pos, i)
        name = names[i]
        if name not in AXES:
            raise InputError(f"table topic joint {name!r} is not x, y or z", path=path)
        sign = JOINT_SIGN[name]
        t_ns.append(stamp or int(log_t))
        axis.append(name)
        rate.append(sign * (vel[i] if i < len(vel) else 0.0) / (2 * np.pi))
        angle.append(sign * np.degrees(pos[i]))
    bad = [a for a in axis if a not in AXES]
    if bad:
        raise InputError(f"table topic: unknown axis label {bad[0]!r} (expected x, y or z)", path=path)
    codes = np.array([AXES.index(a) for a in axis], np.int8)
    return _track(np.asarray(t_ns, np.int64), codes, np.asarray(rate, float), np.asarray(angle, float))


def _track(t_ns: np.ndarray, axis: np.ndarray, rate_hz: np.ndarray, angle_deg: np.ndarray) -> TableTrack:
    """Table messages in time order (stable), rates to the nearest nanohertz."""
    if np.any(t_ns[1:] < t_ns[:-1]):
        order = np.argsort(t_ns, kind="stable")
        t_ns, axis, rate_hz, angle_deg = t_ns[order], axis[order], rate_hz[order], angle_deg[order]
    rate = rate_hz * 1e9  # canonical_rate, one array
    np.round(rate, out=rate)
    rate /= 1e9
    return TableTrack(t_ns, axis, rate, angle_deg)


def _fast_imu_frame(topic: mcap_fast.DecodedTopic, path: Path) -> pl.DataFrame:
    if topic.kind == "json":
        fields = [f for f in JSON_FIELDS if f in topic.frame.columns]
        return _json_frame(topic.frame.select(fields), topic.columns["log_ns"], topic.channel.topic, path)
    if topic.kind != "imu":
        raise mcap_fast.Unsupported(f"DUT topic of schema {topic.schema.name if topic.schema else None}")
    c = topic.take()
    return pl.DataFrame({"t_ns": c["t_ns"], "u": c["x"], "v": c["y"], "w": c["z"]})  # zero-copy


def _fast_joint_index(names: np.ndarray, position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``_joint_axis`` for every message at once (joints named alike in all)."""
    n_msgs, n_joints = position.shape
    if n_joints == 1:
        return np.zeros(n_msgs, np.int64)
    if np.any(names != names[:1]):
        raise mcap_fast.Unsupported("JointState joints renamed between messages")
    speed = np.abs(velocity) if velocity.shape[1] == n_joints else np.zeros_like(position)
    moving = speed.max(axis=1) > 0
    index = np.where(moving, speed.argmax(axis=1), -1)
    moved = position[1:] != position[:-1]
    index[1:] = np.where(~moving[1:] & moved.any(axis=1), moved.argmax(axis=1), index[1:])
    index[0] = max(index[0], 0)
    held = np.maximum.accumulate(np.where(index >= 0, np.arange(n_msgs), 0))  # at rest, unmoved: the previous joint
    return index[held]


def _axis_code(labels: np.ndarray, axes: list) -> np.ndarray:
    """Each label's index into ``axes`` (AXES as the source spells them), -1 for any other."""
    code = np.full(labels.size, -1, np.int8)
    for k, a in enumerate(axes):
        code[labels == a] = k
    return code


def _fast_table_track(topic: mcap_fast.DecodedTopic, path: Path) -> TableTrack:
    if topic.kind == "json":
        frame, log_ns = topic.frame, topic.columns["log_ns"]
        def column(name: str) -> np.ndarray:
            values = frame[name].cast(pl.Float64) if name in frame.columns else pl.Series([None] * frame.height, dtype=pl.Float64)
            return values.fill_null(np.nan).to_numpy()
        t_s = column("t")
        t_ns = np.where(np.isnan(t_s), log_ns, np.round(np.nan_to_num(t_s) * 1e9).astype(np.int64))
        axis = frame["axis"].to_numpy().astype(object) if "axis" in frame.columns else np.full(frame.height, None, object)
        code = _axis_code(axis, AXES)
        if np.any(code < 0):
            raise mcap_fast.Unsupported("table axis other than x, y or z")
        rate, angle = column("rate_hz"), column("angle_deg")
    elif topic.kind == "joint":
        c = topic.take()
        if c["position"].shape[1] == 1:
            name, position = c["name"][:, 0], c["position"][:, 0]
            velocity = c["velocity"][:, 0] if c["velocity"].shape[1] else np.zeros(position.size)
        else:
            index = _fast_joint_index(c["name"], c["position"], c["velocity"])
            rows = np.arange(index.size)
            name, position = c["name"][rows, index], c["position"][rows, index]
            velocity = c["velocity"][rows, index] if c["velocity"].shape[1] else np.zeros(index.size)
        code = _axis_code(name, [a.encode() for a in AXES])
        if np.any(code < 0):
            raise mcap_fast.Unsupported("table joint other than x, y or z")
        sign = np.array([JOINT_SIGN[a] for a in AXES], np.int8)[code]
        t_ns = c["t_ns"]
        rate = sign * velocity  # in place from here: millions of messages
        rate /= 2 * np.pi
        angle = np.degrees(position)
        angle *= sign
    else:
        raise mcap_fast.Unsupported(f"table topic of schema {topic.schema.name if topic.schema else None}")
    return _track(t_ns, code, rate, angle)


def map_table(t_ns: np.ndarray, track: TableTrack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The table message in force (index into ``track``, -1 before the
    first), rate and angle at each DUT stamp (contract section 1).

    Labels hold from the last table message. Angles are linearly interpolated
    between messages of the same run (same axis and rate) after unwrapping
    with the commanded rate, extrapolated at that rate past a run's last
    message, and held during static steps.
    """
    n = t_ns.size
    rate = np.full(n, np.nan)
    angle = np.full(n, np.nan)
    idx = np.searchsorted(track.t_ns, t_ns, side="right") - 1
    if track.t_ns.size == 0:
        return idx, rate, angle
    run, increment = track.runs
    have = idx >= 0
    i = idx[have]
    rate_i, angle_i, t_i = track.rate_hz[i], track.angle_deg[i], track.t_ns[i]  # each gathered once
    rate[have] = rate_i
    nxt = np.minimum(i + 1, track.t_ns.size - 1)
    same_run = (nxt != i) & (run[nxt] == run[i])
    dt_ns = t_ns[have] - t_i
    span_ns = np.where(same_run, track.t_ns[nxt] - t_i, 1)
    step = np.where(same_run, increment[np.minimum(i, increment.size - 1)] if increment.size else 0.0, 0.0)
    interp = angle_i + dt_ns / span_ns * step
    extrap = angle_i + 360.0 * rate_i * dt_ns / 1e9
    angle[have] = np.where(rate_i != 0, np.where(same_run, interp, extrap), angle_i)
    return idx, rate, angle


_LABEL_BLOCK = 1 << 18


def _table_labels(t_ns: np.ndarray, track: TableTrack) -> pl.DataFrame:
    """``map_table`` a block of samples at a time (a sample's labels depend
    only on its own time stamp), so its temporaries stay small; ``axis``
    as the sample table's Enum (one byte a sample). The columns are filled
    in place: blocks kept as chunks would pin the freed temporaries between
    them in the heap."""
    codes = np.r_[track.axis, -1]  # the last entry serves index -1: no message yet
    axis, rate, angle = np.empty(t_ns.size, np.int8), np.empty(t_ns.size), np.empty(t_ns.size)
    for start in range(0, t_ns.size, _LABEL_BLOCK):
        block = slice(start, start + _LABEL_BLOCK)
        index, rate[block], angle[block] = map_table(t_ns[block], track)
        axis[block] = codes[index]
    return pl.DataFrame({
        "axis": pl.Series(np.ma.masked_array(axis.view(np.uint8), axis < 0)).cat.to(pl.Enum(AXES)),  # codes as they are
        "rate_hz": pl.Series(rate).fill_nan(None),
        "angle_deg": pl.Series(angle).fill_nan(None),
    })


def read_mcap_capture(path: Path, meta: DatasetMeta, spec: CaptureSpec | None, limits: Limits) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """One MCAP capture as canonical sample columns, and notes on the topics
    chosen where the defaults were absent."""
    if path.stat().st_size == 0:
        raise InputError("the file is empty", path=path)
    topics = {meta.imu_topic, meta.table_topic}
    try:
        return _capture(mcap_fast.read_topics(path, topics, limits), path, meta, spec, fast=True)
    except mcap_fast.Unsupported:
        return _capture(_read_records(path, topics, limits), path, meta, spec, fast=False)


def _capture(found: dict, path: Path, meta: DatasetMeta, spec: CaptureSpec | None, fast: bool) -> tuple[pl.DataFrame, tuple[str, ...]]:
    imu_key = _choose_topic(found, meta.imu_topic, meta.imu_topic_given, IMU_SCHEMA, path)
    table_key = _choose_topic(found, meta.table_topic, meta.table_topic_given, JOINT_SCHEMA, path)
    if imu_key is None:
        listing = ", ".join(sorted(found)) or "none"
        raise InputError(f"topic {meta.imu_topic!r} is not in the file (topics: {listing})", path=path,
                         hint="set [mcap] imu_topic in dataset.toml")
    notes = tuple(
        f"{path.name}: topic {meta_topic!r} absent; read the only {kind} topic {key!r}"
        for key, meta_topic, kind in ((imu_key, meta.imu_topic, "Imu"), (table_key, meta.table_topic, "JointState"))
        if key is not None and key != meta_topic
    )
    frame = (_fast_imu_frame if fast else _imu_frame)(found[imu_key], path)
    if frame.height == 0:
        raise InputError(f"topic {found[imu_key].channel.topic!r} has no messages", path=path)
    frame = time_ordered(frame)
    source = "file"
    if table_key is not None and found[table_key].count and "axis" not in frame.columns:
        # the track is a temporary, gone before label_columns builds the final columns
        make_track = _fast_table_track if fast else _table_track
        frame = frame.hstack(_table_labels(frame["t_ns"].to_numpy(), make_track(found[table_key], path)).get_columns())
        source = "table"
    for name in ("u", "v", "w"):
        values = frame[name].cast(pl.Float64)
        bad = (values.is_null() | values.is_nan()).arg_true()
        if len(bad):
            raise InputError(f"{name!r} of message {int(bad[0]) + 1} is not a number", path=path)
    return label_columns(frame, spec, path, label_source=source), notes
