"""Byte layouts of the fixed-layout ROS 2 messages rotcal reads and writes in
bulk: ``sensor_msgs/msg/Imu`` with a given ``frame_id`` and
``sensor_msgs/msg/JointState`` whose names keep their lengths.

CDR (XCDR1, little endian: encapsulation header ``00 01 00 00``) aligns each
primitive to its own size, counted from the end of the 4-byte encapsulation
header; strings are a uint32 length (terminating NUL included), the bytes
and the NUL. With every string length fixed, every field of every message
sits at the same offset, so a block of messages is a strided array.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

CDR_LE = b"\x00\x01\x00\x00"
_ENCAP = len(CDR_LE)


def _align(offset: int, size: int) -> int:
    return (offset + size - 1) // size * size


@dataclass(frozen=True)
class ImuLayout:
    """Offsets (from the start of the message data, encapsulation header
    included) of an Imu message whose ``frame_id`` is ``frame_id_len``
    bytes long (NUL included)."""

    frame_id_len: int
    size: int
    stamp: int
    frame_id: int
    orientation: int
    angular_velocity: int
    linear_acceleration: int


@lru_cache(maxsize=64)  # once per chunk: the layouts are few (bounded: a hostile file may vary them)
def imu_layout(frame_id_len: int) -> ImuLayout:
    body = _align(12 + frame_id_len, 8)  # sec, nanosec, string length, string; then float64s
    return ImuLayout(
        frame_id_len=frame_id_len,
        size=_ENCAP + body + 296,  # quaternion 32, 3 x (covariance 72), 2 x vector 24
        stamp=_ENCAP,
        frame_id=_ENCAP + 12,
        orientation=_ENCAP + body,
        angular_velocity=_ENCAP + body + 104,
        linear_acceleration=_ENCAP + body + 200,
    )


def imu_template(frame_id: str) -> np.ndarray:
    """The bytes of an Imu message with zero stamp and acceleration, identity
    orientation, and covariances marked as REP 145 asks: element 0 = -1 for
    "orientation and angular velocity not provided", zeros for "acceleration
    covariance unknown"."""
    name = frame_id.encode() + b"\x00"
    lay = imu_layout(len(name))
    out = np.zeros(lay.size, np.uint8)
    out[:_ENCAP] = np.frombuffer(CDR_LE, np.uint8)
    out[lay.frame_id - 4 : lay.frame_id] = np.frombuffer(np.uint32(len(name)).tobytes(), np.uint8)
    out[lay.frame_id : lay.frame_id + len(name)] = np.frombuffer(name, np.uint8)
    floats = out[lay.orientation :].view("<f8")
    floats[3] = 1.0   # quaternion w
    floats[4] = -1.0  # orientation_covariance[0]
    floats[16] = -1.0  # angular_velocity_covariance[0]
    return out


@dataclass(frozen=True)
class JointLayout:
    """Offsets in a JointState message with ``n`` joints whose names have
    the byte lengths ``name_lens`` (NUL included), ``n_velocity`` velocities
    and ``n_effort`` efforts; ``counts`` are the (offset, value) pairs of
    every length field, which pin the layout."""

    size: int
    stamp: int
    names: tuple[int, ...]
    name_lens: tuple[int, ...]
    position: int
    velocity: int
    counts: tuple[tuple[int, int], ...]


@lru_cache(maxsize=64)
def joint_layout(frame_id_len: int, name_lens: tuple[int, ...], n_velocity: int, n_effort: int) -> JointLayout:
    n = len(name_lens)
    counts = [(8, frame_id_len)]
    off = _align(12 + frame_id_len, 4)
    counts.append((off, n))
    off += 4
    names = []
    for length in name_lens:
        counts.append((off, length))
        names.append(off + 4)
        off = _align(off + 4 + length, 4)
    starts = []
    for count in (n, n_velocity, n_effort):
        counts.append((off, count))
        start = _align(off + 4, 8) if count else off + 4
        starts.append(start)
        off = start + 8 * count
    return JointLayout(
        size=_ENCAP + off,
        stamp=_ENCAP,
        names=tuple(_ENCAP + o for o in names),
        name_lens=tuple(name_lens),
        position=_ENCAP + starts[0],
        velocity=_ENCAP + starts[1],
        counts=tuple((_ENCAP + o, v) for o, v in counts),
    )


def joint_template(frame_id: str, name_lens: tuple[int, ...], n_velocity: int, n_effort: int) -> tuple[np.ndarray, JointLayout]:
    """A JointState message with every length field set and zero values."""
    name = frame_id.encode() + b"\x00"
    lay = joint_layout(len(name), name_lens, n_velocity, n_effort)
    out = np.zeros(lay.size, np.uint8)
    out[:_ENCAP] = np.frombuffer(CDR_LE, np.uint8)
    for off, value in lay.counts:
        out[off : off + 4] = np.frombuffer(np.uint32(value).tobytes(), np.uint8)
    out[_ENCAP + 12 : _ENCAP + 12 + len(name)] = np.frombuffer(name, np.uint8)
    return out, lay
