"""MCAP captures: ``sensor_msgs/msg/Imu`` (CDR) or JSON messages on the DUT
topic, and an optional table channel (``sensor_msgs/msg/JointState`` or JSON)
whose labels are mapped onto the DUT's time stamps (docs/inputs.md, "MCAP captures").

Files are decoded by ``mcap_fast`` (whole chunks into columns) where it knows
the layouts, else message by message (``mcap_messages``); both feed the same
steps here, and the table channel becomes labels in ``mcap_table``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap.columns import DecodedTopic
from rotcal.ingest.formats.mcap.messages import MessageTopic, decoder, read_records, require
from rotcal.ingest.formats.mcap.records import Unsupported
from rotcal.ingest.formats.mcap.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.ingest.formats.mcap.table import fast_table_track, finite_numbers, json_columns, json_time_ns, table_labels, table_track
from rotcal.ingest.labels import label_columns, time_ordered
from rotcal.ingest.meta import CaptureSpec, DatasetMeta

JSON_FIELDS = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")


def _choose_topic(found: dict[str, MessageTopic], wanted: str, given: bool, schema_name: str, path: Path) -> str | None:
    """``wanted`` if present; else, when the topic was a default, the only
    channel of ``schema_name``; a topic named in dataset.toml must exist."""
    if wanted in found:
        return wanted
    if given:
        listing = ", ".join(sorted(found)) or "none"
        raise InputError(f"topic {wanted!r} is not in the file (topics: {listing})", path=path)
    typed = [t for t, v in found.items() if v.schema is not None and v.schema.name == schema_name]
    return typed[0] if len(typed) == 1 else None


def _imu_frame(topic: MessageTopic, path: Path) -> pl.DataFrame:
    decode = decoder(topic)
    try:
        msgs = [decode(data) for data in topic.rows]
    except Exception as exc:  # a decoder failure is a corrupt message, whatever the library raises
        raise InputError(f"topic {topic.channel.topic!r}: message cannot be decoded ({exc})", path=path) from None
    log_ns = np.asarray(topic.stamps, np.int64)
    if topic.channel.message_encoding == "json":
        return _json_frame(json_columns(msgs, JSON_FIELDS, topic.channel.topic, path), log_ns, topic.channel.topic, path)
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
    t_s = frame["t"].cast(pl.Float64).fill_null(np.nan).to_numpy() if "t" in frame.columns else np.full(frame.height, np.nan)
    return frame.with_columns(t_ns=pl.Series(json_time_ns(t_s, log_ns, topic, path))).drop("t", strict=False)


def _fast_imu_frame(topic: DecodedTopic, path: Path) -> pl.DataFrame:
    if topic.kind == "json":
        fields = [f for f in JSON_FIELDS if f in topic.parsed.columns]
        return _json_frame(finite_numbers(topic.parsed.select(fields)), topic.columns["log_ns"], topic.channel.topic, path)
    if topic.kind != "imu":
        raise Unsupported(f"DUT topic of schema {topic.schema.name if topic.schema else None}")
    c = topic.take()
    return pl.DataFrame({"t_ns": c["t_ns"], "u": c["x"], "v": c["y"], "w": c["z"]})  # zero-copy


def read_mcap_capture(path: Path, meta: DatasetMeta, spec: CaptureSpec | None, limits: Limits,
                      workers: int = 0) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """One MCAP capture as canonical sample columns, and notes on the topics
    chosen where the defaults were absent; ``workers`` as ``parallel.cores``
    reads it."""
    if path.stat().st_size == 0:
        raise InputError("the file is empty", path=path)
    topics = {meta.imu_topic, meta.table_topic}
    try:
        return _capture(mcap_fast.read_topics(path, topics, limits, workers), path, meta, spec, workers, fast=True)
    except Unsupported:
        pass  # read again below, not in this handler: the exception's traceback holds the fast path's chunks
    return _capture(read_records(path, topics, limits), path, meta, spec, workers, fast=False)


def read_capture(path: Path, spec: CaptureSpec | None, meta: DatasetMeta, limits: Limits,
                 workers: int = 0) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """The registry's reader (``ingest.formats``): ``read_mcap_capture``."""
    return read_mcap_capture(path, meta, spec, limits, workers)


def chosen_topics(found: dict, path: Path, meta: DatasetMeta) -> tuple[str, str | None, tuple[str, ...]]:
    """The DUT and table topics read (``found``: every channel by topic) and
    notes on those chosen where the defaults were absent."""
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
    return imu_key, table_key, notes


def _capture(found: dict, path: Path, meta: DatasetMeta, spec: CaptureSpec | None, workers: int, fast: bool) -> tuple[pl.DataFrame, tuple[str, ...]]:
    imu_key, table_key, notes = chosen_topics(found, path, meta)
    require(found[imu_key].schema, found[imu_key].channel, IMU_SCHEMA, path)
    frame = (_fast_imu_frame if fast else _imu_frame)(found[imu_key], path)
    if frame.height == 0:
        raise InputError(f"topic {found[imu_key].channel.topic!r} has no messages", path=path)
    frame = time_ordered(frame)
    source = "file"
    if table_key is not None and found[table_key].count and "axis" not in frame.columns:
        # the track is a temporary, gone before label_columns builds the final columns
        require(found[table_key].schema, found[table_key].channel, JOINT_SCHEMA, path)
        make_track = fast_table_track if fast else table_track
        frame = frame.hstack(table_labels(frame["t_ns"].to_numpy(), make_track(found[table_key], path), workers).get_columns())
        source = "table"
    for name in ("u", "v", "w"):
        values = frame[name].cast(pl.Float64)
        if not values.null_count() and all(np.isfinite(extreme) for extreme in (values.to_numpy().min(), values.to_numpy().max())):
            continue  # two reductions, no copy (a NaN or an infinity is an extreme): the message is looked for only where there is one to write
        bad = (values.is_null() | ~values.is_finite()).arg_true()
        raise InputError(f"{name!r} of message {int(bad[0]) + 1} is not a finite number ({values[int(bad[0])]})", path=path)
    # label_columns checks every other value where it enters (ingest.labels.check_values)
    return label_columns(frame, spec, path, label_source=source), notes
