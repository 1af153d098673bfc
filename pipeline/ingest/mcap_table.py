"""The table channel of an MCAP capture (``sensor_msgs/msg/JointState`` or
JSON): its messages as a track of commanded axis, rate and angle, mapped
onto the DUT's time stamps (docs/inputs.md, "MCAP captures"; the signs of
docs/conventions.md). Read message by message
(``table_track``) or from ``mcap_fast``'s columns (``fast_table_track``);
both give the same track."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.errors import InputError
from rotcal.ingest.mcap_columns import DecodedTopic, Unsupported
from rotcal.ingest.mcap_messages import MessageTopic, decoder
from rotcal.model.physics import AXES, JOINT_SIGN


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


def table_track(topic: MessageTopic, path: Path) -> TableTrack:
    decode = decoder(topic, path)
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


def _fast_joint_index(names: np.ndarray, position: np.ndarray, velocity: np.ndarray) -> np.ndarray:
    """``_joint_axis`` for every message at once (joints named alike in all)."""
    n_msgs, n_joints = position.shape
    if n_joints == 1:
        return np.zeros(n_msgs, np.int64)
    if np.any(names != names[:1]):
        raise Unsupported("JointState joints renamed between messages")
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


def fast_table_track(topic: DecodedTopic, path: Path) -> TableTrack:
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
            raise Unsupported("table axis other than x, y or z")
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
            raise Unsupported("table joint other than x, y or z")
        sign = np.array([JOINT_SIGN[a] for a in AXES], np.int8)[code]
        t_ns = c["t_ns"]
        rate = sign * velocity  # in place from here: millions of messages
        rate /= 2 * np.pi
        angle = np.degrees(position)
        angle *= sign
    else:
        raise Unsupported(f"table topic of schema {topic.schema.name if topic.schema else None}")
    return _track(t_ns, code, rate, angle)


def map_table(t_ns: np.ndarray, track: TableTrack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The table message in force (index into ``track``, -1 before the
    first), rate and angle at each DUT stamp (docs/inputs.md, "Table channel").

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


def table_labels(t_ns: np.ndarray, track: TableTrack) -> pl.DataFrame:
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
