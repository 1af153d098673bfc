"""The table channel of an MCAP capture (``sensor_msgs/msg/JointState`` or
JSON): its messages as a track of commanded axis, rate and angle, mapped
onto the DUT's time stamps (docs/inputs.md, "MCAP captures"; the signs of
docs/conventions.md). Read message by message
(``table_track``) or from ``mcap_fast``'s columns (``fast_table_track``);
both give the same track."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.errors import InputError
from rotcal.ingest.formats.mcap.columns import DecodedTopic
from rotcal.ingest.formats.mcap.json_lines import NUMBER_FIELDS, TEXT_FIELDS
from rotcal.ingest.formats.mcap.messages import MessageTopic, decoder
from rotcal.ingest.formats.mcap.records import Unsupported
from rotcal.ingest.labels import MAX_ABS_TIME_S
from rotcal.model.physics import AXES, JOINT_SIGN
from rotcal.parallel import cores


@dataclass(frozen=True)
class TableTrack:
    """Table-channel messages in time order: the commanded axis, rate and angle."""

    t_ns: np.ndarray
    axis: np.ndarray  # int8 index into AXES
    rate_hz: np.ndarray
    angle_deg: np.ndarray

    def law(self, lo: int, hi: int) -> tuple[np.ndarray, ...]:
        """Entries ``lo`` to ``hi - 1`` of the table's law: entry 0 for "no
        message yet" (NaN labels), entry k for message k - 1: the axis code,
        rate, angle, time and the factors (p, q, r) of the angle after it,
        ``angle + dt_ns * p / q * r`` (three cases in one expression, each
        factor exact where it is 1 or 0, so bit for bit the angles of each
        case's own formula). Within a run (same axis and rate) the angle is
        interpolated towards the next message's, after unwrapping with the
        commanded rate (only sin and cos of theta are used, so no running sum
        is needed); after a run's last message it is extrapolated at the
        rate; at rest it is held (``dt * 0 / 1 * -1`` is -0.0, which leaves
        every angle, -0.0 included, as it is). Computed a block at a time:
        its temporaries stay small."""
        begin, stop = max(lo - 1, 0), min(hi - 1, self.t_ns.size)  # the entries' messages, and the one after
        with_next = slice(begin, min(stop + 1, self.t_ns.size))
        axis, rate, angle, t_ns = self.axis[with_next], self.rate_hz[with_next], self.angle_deg[with_next], self.t_ns[with_next]
        k = stop - begin
        span = np.diff(t_ns)  # to the next message, where there is one (all but possibly the last)
        same_run = (axis[1:] == axis[:-1]) & (rate[1:] == rate[:-1])
        expected = 360.0 * rate[:-1] * span / 1e9
        increment = expected + (np.diff(angle) - expected + 180.0) % 360.0 - 180.0
        # the cases by masked copies, not index lists: a run covers nearly every message
        p, q, r, m = 360.0 * rate[:k], np.full(k, 1e9), np.ones(k), span.size
        np.copyto(p[:m], 1.0, where=same_run)
        np.copyto(q[:m], span, where=same_run)
        np.copyto(r[:m], increment, where=same_run)
        held = rate[:k] == 0
        np.copyto(p, 0.0, where=held)
        np.copyto(q, 1.0, where=held)
        np.copyto(r, -1.0, where=held)
        law = (axis[:k], rate[:k], angle[:k], t_ns[:k], p, q, r)
        if lo > 0:
            return law
        return tuple(_after(before, v) for before, v in zip((-1, np.nan, np.nan, 0, 0.0, 1.0, -1.0), law))


def _after(before, values: np.ndarray) -> np.ndarray:
    """``values`` after one entry ``before``, of their type."""
    return np.concatenate((np.array([before], values.dtype), values))


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


def _number(value, name: str, k: int, topic: str, path: Path) -> float | None:
    """One JSON number field (None where absent); NaN, infinity, numbers
    beyond float and anything else refused."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise InputError(f"topic {topic!r}: {name!r} of message {k + 1} is not a number ({value!r:.40})", path=path)
    try:
        number = float(value)
    except OverflowError:  # an integer beyond float
        number = np.inf
    if not np.isfinite(number):
        raise InputError(f"topic {topic!r}: {name!r} of message {k + 1} is not a finite number ({value!r:.40})", path=path)
    return number


def json_columns(msgs: list, fields: tuple[str, ...], topic: str, path: Path) -> pl.DataFrame:
    """The ``fields`` present in JSON messages (each an object) as columns:
    numbers as Float64 and text as String, null where absent."""
    for k, m in enumerate(msgs):
        if not isinstance(m, dict):
            raise InputError(f"topic {topic!r}: message {k + 1} is not a JSON object", path=path)
    columns = {}
    for name in (f for f in fields if any(f in m for m in msgs)):
        values = [m.get(name) for m in msgs]
        if name in NUMBER_FIELDS:
            columns[name] = pl.Series(name, [_number(v, name, k, topic, path) for k, v in enumerate(values)], pl.Float64)
            continue
        wrong = [k for k, v in enumerate(values) if v is not None and not isinstance(v, str)]
        if wrong:
            raise InputError(f"topic {topic!r}: {name!r} of message {wrong[0] + 1} is not text", path=path)
        columns[name] = pl.Series(name, values, pl.String)
    return pl.DataFrame(columns, height=len(msgs))


def finite_numbers(frame: pl.DataFrame) -> pl.DataFrame:
    """``frame`` (JSON messages parsed by polars) if every field is of its
    kind and every number finite; else ``Unsupported``: the per-message path
    words what is wrong."""
    for name, dtype in frame.schema.items():
        if name in NUMBER_FIELDS and not (dtype.is_numeric() or dtype == pl.Null):
            raise Unsupported(f"JSON field {name!r} holds other than numbers")
        if name in TEXT_FIELDS and dtype not in (pl.String, pl.Null):
            raise Unsupported(f"JSON field {name!r} holds other than text")
        if dtype.is_float() and not frame[name].is_finite().all():
            raise Unsupported(f"JSON field {name!r} holds a number that is not finite")
    return frame


def json_time_ns(t_s: np.ndarray, log_ns: np.ndarray, topic: str, path: Path) -> np.ndarray:
    """JSON ``t`` (s; NaN where absent: the log time) as int64 nanoseconds."""
    bad = np.abs(t_s) >= MAX_ABS_TIME_S  # an absent time (NaN) compares false
    if bad.any():
        k = int(bad.argmax())
        raise InputError(f"topic {topic!r}: 't' of message {k + 1} is not a time in seconds ({t_s[k]:g})", path=path)
    t_ns = t_s * 1e9
    np.round(t_ns, out=t_ns)
    absent = np.isnan(t_ns)
    if not absent.any():  # every message has its time: no mask, no second array
        return t_ns.astype(np.int64)
    t_ns[absent] = 0.0
    return np.where(absent, log_ns, t_ns.astype(np.int64))


def _json_track(frame: pl.DataFrame, log_ns: np.ndarray, topic: str, path: Path) -> TableTrack:
    """The table's JSON messages (checked fields, either path) as a track."""
    def column(name: str) -> np.ndarray:
        values = frame[name].cast(pl.Float64) if name in frame.columns else pl.Series([None] * frame.height, dtype=pl.Float64)
        return values.fill_null(np.nan).to_numpy()
    # each label's index into AXES through the Enum's codes (a label of another spelling: null), -1 for none
    axis = frame["axis"] if "axis" in frame.columns else pl.Series([None] * frame.height, dtype=pl.String)
    code = axis.cast(pl.Enum(AXES), strict=False).to_physical().cast(pl.Int8).fill_null(-1).to_numpy()
    if np.any(code < 0):
        label = axis[int(np.argmax(code < 0))]
        raise InputError(f"table topic {topic!r}: unknown axis label {label!r} (expected x, y or z)", path=path)
    return _track(json_time_ns(column("t"), log_ns, topic, path), code, column("rate_hz"), column("angle_deg"), topic, path)


def table_track(topic: MessageTopic, path: Path) -> TableTrack:
    decode = decoder(topic)
    log_ns = np.asarray(topic.stamps, np.int64)
    name = topic.channel.topic
    try:
        msgs = [decode(data) for data in topic.rows]
    except Exception as exc:  # a decoder failure is a corrupt message, whatever the library raises
        raise InputError(f"table topic {name!r}: message cannot be decoded ({exc})", path=path) from None
    if topic.channel.message_encoding == "json":
        return _json_track(json_columns(msgs, ("t", "axis", "rate_hz", "angle_deg"), name, path), log_ns, name, path)
    t_ns, axis, rate, angle = [], [], [], []
    previous = None
    for m, log_t in zip(msgs, log_ns):
        stamp = m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec
        names, pos, vel = list(m.name), list(m.position), list(m.velocity)
        if not names or len(pos) != len(names):
            raise InputError(f"table topic {name!r}: a JointState message without one position per joint", path=path)
        i = _joint_axis(names, pos, vel, previous)
        previous = (names, pos, i)
        if names[i] not in AXES:
            raise InputError(f"table topic joint {names[i]!r} is not x, y or z", path=path)
        sign = JOINT_SIGN[names[i]]
        t_ns.append(stamp or int(log_t))
        axis.append(names[i])
        rate.append(sign * (vel[i] if i < len(vel) else 0.0) / (2 * np.pi))
        angle.append(sign * np.degrees(pos[i]))
    codes = np.array([AXES.index(a) for a in axis], np.int8)
    return _track(np.asarray(t_ns, np.int64), codes, np.asarray(rate, float), np.asarray(angle, float), name, path, cdr=True)


def _track(t_ns: np.ndarray, axis: np.ndarray, rate_hz: np.ndarray, angle_deg: np.ndarray, topic: str, path: Path,
           cdr: bool = False) -> TableTrack:
    """Table messages in time order (stable), rates to the nearest nanohertz;
    rates and angles must be finite (in JSON, NaN marks one not given)."""
    for label, values in (("rate", rate_hz), ("angle", angle_deg)):
        if cdr and values.size and np.isfinite(values.min()) and np.isfinite(values.max()):
            continue  # two reductions, no mask: a NaN or an infinity is an extreme
        bad = ~np.isfinite(values) if cdr else np.isinf(values)
        if bad.any():
            k = int(bad.argmax())
            raise InputError(f"table topic {topic!r}: the {label} of message {k + 1} is not a finite number ({values[k]})", path=path)
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
        return _json_track(finite_numbers(topic.parsed), topic.columns["log_ns"], topic.channel.topic, path)
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
    return _track(t_ns, code, rate, angle, topic.channel.topic, path, cdr=True)


def map_table(t_ns: np.ndarray, law: tuple[np.ndarray, ...], first: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The axis code (-1 before the first message), rate and angle at each
    DUT stamp of ``t_ns`` (ascending; docs/inputs.md, "Table channel"), given
    the messages in force over them (``TableTrack.law``) and the
    first sample under each (``first``, from 0).

    Labels hold from the last table message. Angles are linearly interpolated
    between messages of the same run (same axis and rate) after unwrapping
    with the commanded rate, extrapolated at that rate past a run's last
    message, and held during static steps. Each message's values are
    repeated over its samples: no search, no gather.
    """
    counts = np.diff(np.concatenate((first, [t_ns.size])))
    axis, rate, angle, t_msg, p, q, r = (np.repeat(v, counts) for v in law)
    term = (t_ns - t_msg).astype(np.float64)
    term *= p
    term /= q
    term *= r
    angle += term
    return axis, rate, angle


_LABEL_BLOCK = 1 << 15  # a block's temporaries stay in the cache, and the heap reuses them


def table_labels(t_ns: np.ndarray, track: TableTrack, workers: int = 1) -> pl.DataFrame:
    """``map_table`` a block of samples at a time (a sample's labels depend
    only on its own time stamp), so its temporaries stay small (and fast:
    in the cache, no fresh pages), the blocks shared out over
    ``parallel.cores(workers)`` threads (numpy releases the GIL); ``t_ns``
    ascending (``labels.time_ordered``); ``axis`` as the sample table's Enum
    (one byte a sample). The columns are filled in place: blocks kept as
    chunks would pin the freed temporaries between them in the heap."""
    axis, rate, angle = np.empty(t_ns.size, np.int8), np.empty(t_ns.size), np.empty(t_ns.size)

    def label(start: int) -> None:
        block = slice(start, start + _LABEL_BLOCK)
        t_block = t_ns[block]
        # the entries of the law in force over the block (entry k: k messages at or before the stamp)
        lo, hi = (int(k) for k in np.searchsorted(track.t_ns, t_block[[0, -1]], side="right") + (0, 1))
        # the first sample of the block under each: one search a message, within the block
        under = np.searchsorted(t_block, track.t_ns[max(lo - 1, 0) : hi - 1], side="left")
        if lo == 0:
            under = _after(0, under)
        axis[block], rate[block], angle[block] = map_table(t_block, track.law(lo, hi), under)

    starts = range(0, t_ns.size, _LABEL_BLOCK)
    threads = min(cores(workers), len(starts))
    if threads > 1:
        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(label, starts))
    else:
        list(map(label, starts))
    return pl.DataFrame({
        "axis": pl.Series(np.ma.masked_array(axis.view(np.uint8), axis < 0)).cat.to(pl.Enum(AXES)),  # codes as they are
        "rate_hz": pl.Series(rate).fill_nan(None),
        "angle_deg": pl.Series(angle).fill_nan(None),
    })
