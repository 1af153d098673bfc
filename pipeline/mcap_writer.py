"""Write captures as MCAP: the DUT as ``sensor_msgs/msg/Imu`` (CDR) or JSON
messages, the table as ``sensor_msgs/msg/JointState`` (CDR) or JSON (contract
section 2). Used by the simulator; zstd-compressed chunks."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import polars as pl
from mcap.writer import CompressionType, Writer
from mcap_ros2.writer import Writer as Ros2Writer

from pipeline import ros2_msgdefs
from pipeline.physics import JOINT_SIGN

_UNKNOWN_COV = [-1.0] + [0.0] * 8  # REP 145: covariance element 0 = -1 marks "not provided"


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}


def _write_cdr(writer: Ros2Writer, samples: pl.DataFrame, table: pl.DataFrame, imu_topic: str, table_topic: str) -> None:
    imu_schema = writer.register_msgdef("sensor_msgs/msg/Imu", ros2_msgdefs.IMU)
    joint_schema = writer.register_msgdef("sensor_msgs/msg/JointState", ros2_msgdefs.JOINT_STATE)
    for t_ns, axis, rate, angle in table.iter_rows():
        sign = JOINT_SIGN[axis]
        writer.write_message(table_topic, joint_schema, {
            "header": {"stamp": _stamp(t_ns), "frame_id": "table"}, "name": [axis],
            "position": [sign * np.deg2rad(angle)], "velocity": [sign * 2 * np.pi * rate], "effort": [],
        }, log_time=t_ns, publish_time=t_ns)
    for t_ns, u, v, w in samples.select("t_ns", "u", "v", "w").iter_rows():
        writer.write_message(imu_topic, imu_schema, {
            "header": {"stamp": _stamp(t_ns), "frame_id": "dut"},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "orientation_covariance": _UNKNOWN_COV,
            "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular_velocity_covariance": _UNKNOWN_COV,
            "linear_acceleration": {"x": u, "y": v, "z": w}, "linear_acceleration_covariance": [0.0] * 9,
        }, log_time=t_ns, publish_time=t_ns)


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
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with tmp.open("wb") as fh:
            if encoding == "cdr":
                writer = Ros2Writer(fh, compression=CompressionType.ZSTD)
                _write_cdr(writer, samples, table, imu_topic, table_topic)
                writer.finish()
            else:
                _write_json(Writer(fh, compression=CompressionType.ZSTD), samples, table, imu_topic, table_topic)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path
