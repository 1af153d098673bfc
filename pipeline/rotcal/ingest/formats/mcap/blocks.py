"""An MCAP capture read chunk by chunk, in memory bounded by a block of
samples: the MCAP format's block reader (``ingest.formats``), ``open_capture``
gives a ``ingest.formats.blocks.RawStream`` whose ``blocks()`` yields the capture's
canonical sample columns in time order, a block at a time, with exactly the
values the in-memory reader gives.

An MCAP capture of CDR ``sensor_msgs/msg/Imu`` with an optional
``JointState`` table channel is read by ``fast.iter_topic_batches``
a batch of chunks at a time. A first pass checks what the in-memory reader
checks (topics, schemas, values, time order) and keeps the decoded
columns on disk (``ingest.spill``: 32 bytes a sample, the table's messages
as many a message, none in memory), and the positions and values where
stamps repeat (for the time base's duplicate check). Each pass of
``blocks()`` then reads the DUT's samples and the table's messages back
from there (where the disk is short, it decompresses and decodes the
capture again, following the two channels with two readers), the table's
messages held for the time a block spans (the message in force at its
first sample carried over, one past its last sample read ahead), and maps
them onto the block's stamps with ``table.table_labels``'s rule (labels
hold from the last message; angles interpolated within a run, extrapolated
at the commanded rate past its end; docs/inputs.md, "Table channel"); the
first pass of ``blocks()`` to go through keeps the labels
(``spill.replayed``), and the later ones read them back beside the samples.

Whatever this reader does not take (JSON messages, layouts the fast path
does not decode, samples or table messages out of time order, multi-joint
tables, a value the in-memory reader refuses, ``[[capture]]`` angles from
``theta0_deg``) raises ``NotBlockwise``: the capture is read whole.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.blocks import COLUMNS, NotBlockwise, RawStream, read_whole
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap.columns import DecodedTopic
from rotcal.ingest.formats.mcap.messages import require
from rotcal.ingest.formats.mcap.reader import chosen_topics
from rotcal.ingest.formats.mcap.records import McapFile, Unsupported
from rotcal.ingest.formats.mcap.ros2_msgdefs import IMU_SCHEMA, JOINT_SCHEMA
from rotcal.ingest.formats.mcap.table import TableTrack, fast_table_track, table_labels
from rotcal.ingest.labels import MAX_ABS_VALUE, label_columns
from rotcal.ingest.meta import CaptureSpec, DatasetMeta
from rotcal.ingest.spill import Spill, replayed, room_for
from rotcal.tables import conform, schema

_STAMP_BLOCK = 1 << 16  # stamps read back a block at a time (the time base's temporaries: about 80 bytes a stamp)
SAMPLE_COLUMNS = {"t_ns": np.int64, "x": np.float64, "y": np.float64, "z": np.float64}
TABLE_COLUMNS = {"t_ns": np.int64, "axis": np.int8, "rate_hz": np.float64, "angle_deg": np.float64}
SPILL_NOTE = ("decompressed and decoded again on each pass over the capture: too little free disk in the temporary "
              "directory to keep its decoded samples (docs/streaming.md)")


@dataclass(eq=False)
class _Seen:
    """What the first pass learns of one decoded channel."""

    count: int = 0
    last_ns: int = np.iinfo(np.int64).min
    ordered: bool = True
    refused: bool = False  # a value the in-memory reader refuses: it words the error
    spill: Spill | None = None  # Imu: the stamps (and the channels, when kept) on disk; table: its messages
    tie_at: list = field(default_factory=list)  # Imu: positions i with t[i + 1] == t[i], and i + 1
    tie_values: list = field(default_factory=list)
    previous: tuple = ()  # Imu: the last sample (t, x, y, z) of the batch before
    low_ns: int = 0
    high_ns: int = 0
    peak_angle_deg: float = 0.0  # table: the largest |angle| and |rate| seen, for the label bound
    peak_rate_hz: float = 0.0

    def ordered_from(self, t_ns: np.ndarray) -> None:
        self.ordered &= bool(t_ns[0] >= self.last_ns and np.all(t_ns[1:] >= t_ns[:-1]))
        if self.count == 0:
            self.low_ns = int(t_ns[0])
        self.last_ns = self.high_ns = int(t_ns[-1])
        self.count += t_ns.size


def _samples_batch(seen: _Seen, c: dict[str, np.ndarray], keep: bool) -> None:
    t_ns, xyz = c["t_ns"], [c["x"], c["y"], c["z"]]
    seen.refused |= any(not np.all(np.abs(a) <= MAX_ABS_VALUE) for a in xyz)  # NaN fails too
    if seen.spill is None:
        seen.spill = Spill(SAMPLE_COLUMNS if keep else {"t_ns": np.int64})
    seen.spill.append(c)
    # repeated stamps: the values on both sides, for the duplicate check (the batch before's last sample too)
    t = np.r_[seen.previous[0], t_ns] if seen.previous else t_ns
    first = seen.count - (1 if seen.previous else 0)
    tie = np.flatnonzero(t[1:] == t[:-1])
    if tie.size:
        values = [np.r_[p, a] for p, a in zip(seen.previous[1:], xyz)] if seen.previous else xyz
        at = np.unique(np.r_[tie, tie + 1])
        seen.tie_at.append(first + at)
        seen.tie_values.append(np.column_stack([v[at] for v in values]))
    seen.previous = (t_ns[-1], *(a[-1] for a in xyz))
    seen.ordered_from(t_ns)


def _table_batch(seen: _Seen, topic: DecodedTopic, path: Path, keep: bool) -> None:
    if topic.columns["position"].shape[1] != 1:
        raise NotBlockwise("a table of several joints: which joint moves depends on the message before")
    seen.ordered_from(topic.columns["t_ns"])
    try:
        track = fast_table_track(topic, path)
    except (InputError, Unsupported):
        raise NotBlockwise("table messages the in-memory reader refuses or reads message by message") from None
    seen.peak_angle_deg = max(seen.peak_angle_deg, float(np.abs(track.angle_deg).max()))
    seen.peak_rate_hz = max(seen.peak_rate_hz, float(np.abs(track.rate_hz).max()))
    if keep:
        seen.spill = seen.spill or Spill(TABLE_COLUMNS)
        seen.spill.append({name: getattr(track, name) for name in TABLE_COLUMNS})


def _room(path: Path, limits: Limits, messages: int | None) -> bool:
    """Whether the temporary directory holds the capture's decoded columns
    (32 bytes a message of any channel: ``messages``, else counted from the
    message indexes; twice the file's size where they cannot be counted)."""
    if messages is None:
        try:
            with path.open("rb") as fh:
                messages = sum(mcap_fast._message_counts(fh, McapFile(path, limits))[0].values())
        except (Unsupported, InputError, OSError):
            return room_for(2 * path.stat().st_size)
    return room_for(32 * messages)


def message_counts(path: Path, limits: Limits) -> list[int]:
    """The messages of each channel of an MCAP file, from its message
    indexes (the most: its samples, for a capture whose table channel is
    slower); none where it has none the fast reader can count."""
    try:
        with path.open("rb") as fh:
            return list(mcap_fast._message_counts(fh, McapFile(path, limits))[0].values())
    except (Unsupported, InputError, OSError):
        return []


def _first_pass(path: Path, meta: DatasetMeta, limits: Limits, workers: int,
                keep: bool) -> tuple[dict, dict[str, _Seen]]:
    """Every channel by topic, and what the first pass over the chunks learnt
    of the decoded ones (their columns kept on disk where ``keep``, else the stamps)."""
    seen: dict[str, _Seen] = {}
    batches = mcap_fast.iter_topic_batches(path, {meta.imu_topic, meta.table_topic}, limits, workers)
    try:
        while True:
            for name, topic in next(batches).items():
                mine = seen.setdefault(name, _Seen())
                if topic.kind == "imu":
                    _samples_batch(mine, topic.take(), keep)
                elif topic.kind == "joint":
                    _table_batch(mine, topic, path, keep)
                else:
                    raise NotBlockwise(f"topic {name!r}: JSON messages")
    except StopIteration as done:
        return done.value, seen
    except Unsupported:
        raise NotBlockwise("a layout the fast path does not decode") from None


def _stamps(seen: _Seen) -> Callable[[], Iterator[np.ndarray]]:
    """The capture's stamps as written by the first pass, a block at a time."""
    spill = seen.spill
    assert spill is not None

    def blocks() -> Iterator[np.ndarray]:
        return (piece["t_ns"] for piece in spill.pieces(_STAMP_BLOCK, ("t_ns",)))
    return blocks


def _window(track: TableTrack, t_first: int) -> TableTrack:
    """The messages from the one in force at ``t_first`` on."""
    start = max(int(np.searchsorted(track.t_ns, t_first, "right")) - 1, 0)
    return TableTrack(track.t_ns[start:], track.axis[start:], track.rate_hz[start:], track.angle_deg[start:])


def _joined(a: TableTrack, b: TableTrack) -> TableTrack:
    return TableTrack(*(np.concatenate([x, y]) for x, y in ((a.t_ns, b.t_ns), (a.axis, b.axis), (a.rate_hz, b.rate_hz),
                                                             (a.angle_deg, b.angle_deg))))


def _following(path: Path, topic: str, channel_id: int, limits: Limits, workers: int) -> Iterator[DecodedTopic]:
    """One channel's messages, a batch at a time, the other channels' chunks skipped."""
    for batch in mcap_fast.iter_topic_batches(path, {topic}, limits, workers, only=frozenset({channel_id})):
        if topic in batch:
            yield batch[topic]


def _sources(path: Path, found: dict, keys: tuple[str, str | None], seen: tuple[_Seen, _Seen | None], limits: Limits,
             workers: int, block: int) -> tuple[Iterator[dict[str, np.ndarray]], Iterator[TableTrack] | None]:
    """For one pass: the DUT's sample columns (t_ns, x, y, z) and the table's
    messages (None without a table channel), read back from the first
    pass's spills, or, where it kept only the stamps, decoded again."""
    (imu_key, table_key), (imu, table) = keys, seen
    assert imu.spill is not None
    if "x" in imu.spill.dtypes:
        tables = None if table is None or table.spill is None else \
            (TableTrack(**piece) for piece in table.spill.pieces(block))  # a block's worth: the labels' temporaries
        return imu.spill.pieces(block), tables
    samples = (topic.take() for topic in _following(path, imu_key, found[imu_key].channel.id, limits, workers))
    if table_key is None:
        return samples, None
    return samples, (fast_table_track(t, path) for t in _following(path, table_key, found[table_key].channel.id, limits,
                                                                    workers))


def _raw_blocks(samples: Iterator[dict[str, np.ndarray]], tables: Iterator[TableTrack] | None,
                block: int) -> Iterator[pl.DataFrame]:
    """The DUT's samples (t_ns, u, v, w, and axis, rate_hz, angle_deg from
    the table's messages where it has them), ``block`` rows at a time, before the time base."""
    track, more = None, tables is not None
    pending: list[dict[str, np.ndarray]] = []
    held_rows = 0
    for columns in chain(samples, [None]):  # None: the end, the rest is the last block
        if columns is not None:
            pending.append(columns)
            held_rows += columns["t_ns"].size
            if held_rows < block:
                continue
        joined = {k: np.concatenate([p[k] for p in pending]) for k in ("t_ns", "x", "y", "z")} if pending else None
        if joined is None:
            break
        cut = joined["t_ns"].size if columns is None else block * (joined["t_ns"].size // block)
        rest = {k: v[cut:] for k, v in joined.items()}
        pending, held_rows = ([rest], rest["t_ns"].size) if rest["t_ns"].size else ([], 0)
        for a in range(0, cut, block):
            t_ns = joined["t_ns"][a : min(a + block, cut)]
            frame = pl.DataFrame({"t_ns": t_ns, "u": joined["x"][a : a + t_ns.size], "v": joined["y"][a : a + t_ns.size],
                                  "w": joined["z"][a : a + t_ns.size]})
            if tables is None:
                yield frame
                continue
            while more and (track is None or track.t_ns.size == 0 or track.t_ns[-1] <= t_ns[-1]):
                nxt = next(tables, None)
                if nxt is None:
                    more = False
                elif nxt.t_ns.size:
                    track = nxt if track is None else _joined(track, nxt)
            if track is None:  # the table topic holds no message: no labels to join
                yield frame
                continue
            track = _window(track, int(t_ns[0]))
            yield frame.hstack(table_labels(t_ns, track).get_columns())  # the track: the window around the block


def _canonical(frame: pl.DataFrame, spec: CaptureSpec | None, path: Path, source: str, capture: str) -> pl.DataFrame:
    """One block's canonical columns, as ``label_columns`` and ``load_dataset`` make them."""
    frame = label_columns(frame, spec, path, label_source=source).with_columns(capture=pl.lit(capture))
    return conform(frame, "samples").select(COLUMNS)


def open_capture(path: Path, meta: DatasetMeta, spec: CaptureSpec | None, limits: Limits, workers: int, block: int,
                 capture: str, messages: int | None) -> RawStream:
    """The registry's block reader (``ingest.formats``; ``ingest.formats.blocks.open_stream``
    calls it): the capture's samples ``block`` rows at a time, the stamps,
    where they repeat, and the spills; ``NotBlockwise`` for what it does not
    take (the module's docstring)."""
    keep = _room(path, limits, messages)
    found, seen = _first_pass(path, meta, limits, workers, keep)
    imu_key, table_key, notes = chosen_topics(found, path, meta)
    # the in-memory reader's checks, in its order (mcap_source._capture)
    require(found[imu_key].schema, found[imu_key].channel, IMU_SCHEMA, path)
    imu = seen.get(imu_key, _Seen())
    if imu.count == 0:
        raise InputError(f"topic {found[imu_key].channel.topic!r} has no messages", path=path)
    if not imu.ordered or imu.refused:
        raise NotBlockwise("samples out of time order, or a value the in-memory reader refuses")
    table = seen.get(table_key) if table_key is not None else None
    if table is not None and table.count:
        require(found[table_key].schema, found[table_key].channel, JOINT_SCHEMA, path)
        span_s = (max(imu.high_ns, table.high_ns) - min(imu.low_ns, table.low_ns)) / 1e9
        # the largest angle a sample's label can reach: a message's angle advanced at its rate over the span
        reach_deg = table.peak_angle_deg + 360.0 * table.peak_rate_hz * span_s
        if not table.ordered or table.refused or reach_deg > MAX_ABS_VALUE:
            raise NotBlockwise("table messages out of time order, or labels the in-memory reader may refuse")
        source: str | None = "table"
    else:
        table_key, table = None, None
        if spec is not None and spec.theta0_deg is not None and spec.rate_hz is not None:
            raise NotBlockwise("angles from [[capture]] theta0_deg: counted from the capture's first stamp")
        source = "toml" if spec is not None and (spec.axis or spec.rate_hz is not None) else None
    ties = None
    if imu.tie_at:
        at, first = np.unique(np.concatenate(imu.tie_at), return_index=True)
        ties = (at, np.concatenate(imu.tie_values)[first])
    # the spills of the other channels are not read again
    for other in (s.spill for s in seen.values() if s is not imu and s is not table):
        if other is not None:
            other.close()

    def labelled() -> Iterator[pl.DataFrame]:
        samples, tables = _sources(path, found, (imu_key, table_key), (imu, table), limits, workers, block)
        for frame in _raw_blocks(samples, tables, block):
            yield _canonical(frame, spec, path, source or "file", capture)

    def unlabelled() -> Iterator[pl.DataFrame]:
        assert imu.spill is not None
        for piece in imu.spill.pieces(block):
            yield pl.DataFrame({"t_ns": piece["t_ns"], "u": piece["x"], "v": piece["y"], "w": piece["z"]})

    def table_no_more() -> None:  # the labels are kept: the table's messages are not read again
        if table is not None and table.spill is not None:
            table.spill.close()
    labels = {c: schema("samples").polars_schema[c] for c in COLUMNS[4:]}
    read = replayed(labelled, labels, imu.count, unlabelled, table_no_more) if keep else labelled

    def whole() -> RawStream:
        return read_whole(path, meta, spec, limits, workers, capture)
    return RawStream(capture, imu.count, source, meta.angle_source, notes if keep else (*notes, SPILL_NOTE), whole, read,
                     _stamps(imu), ties, _files=tuple(s.spill for s in (imu, table) if s is not None))
