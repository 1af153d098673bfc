"""Where a decompressed chunk's message records are (``mcap_fast``): each
channel's records from the chunk's message index records, located with
array arithmetic and checked to tile the chunk exactly: a writer's run of
one channel's messages of one size, back to back, is checked with two
strided eight-byte reads a message, anything else record by record; the
gaps between them hold the chunk's other records (schemas, channels).
Anything that does not tile raises ``Unsupported`` (the per-message path
then words the error)."""

from __future__ import annotations

import struct

import numpy as np
from mcap.opcode import Opcode

from rotcal.ingest.formats.mcap.columns import MESSAGE_HEADER, Records, fields
from rotcal.ingest.formats.mcap.records import Unsupported

_MESSAGE_HEAD = struct.Struct("<BQH")  # a message record's opcode, length and channel id


def ascending(offsets: np.ndarray) -> np.ndarray:
    """``offsets`` in ascending order: as writers index them, or sorted
    (stable sort: a merge of ascending runs, such as channels' concatenated offsets)."""
    return offsets if np.all(offsets[1:] > offsets[:-1]) else np.sort(offsets, kind="stable")


def indexed(raw: np.ndarray, indexes: list[bytes]) -> dict[int, Records]:
    """Each channel's message records in a decompressed chunk, from the
    chunk's message indexes, each offset inside the chunk."""
    parts: dict[int, list[np.ndarray]] = {}
    for index in indexes:
        channel_id, length = struct.unpack_from("<HI", index, 0)
        pairs = np.frombuffer(index, "<u8", count=length // 16 * 2, offset=6).reshape(-1, 2)
        parts.setdefault(channel_id, []).append(pairs[:, 1].astype(np.int64))
    by_channel = {}
    for channel_id, offsets in parts.items():
        records = Records.at(raw, offsets[0] if len(offsets) == 1 else np.concatenate(offsets))
        if records.count and (records.starts[0] < 0 or records.starts[-1] > raw.size - MESSAGE_HEADER):
            raise Unsupported("message index points outside its chunk")
        if records.count:
            by_channel[channel_id] = records
    return by_channel


def uniform_run(records: Records, channel_id: int) -> Records | None:
    """``records`` marked uniform if they are messages of ``channel_id``,
    each ``step`` bytes, back to back (a writer's run of one channel's
    messages of one size): two strided reads of eight bytes a record."""
    step = records.step if records.count > 1 else 9 + int(fields(records, 1, "<u8")[0])
    if not MESSAGE_HEADER <= step <= records.raw.size:
        return None
    records = Records(records.raw, records.starts, step)
    head = int.from_bytes(_MESSAGE_HEAD.pack(Opcode.MESSAGE, step - 9, channel_id), "little")
    first, second = head & (1 << 64) - 1, head >> 24  # opcode and length; the rest of the length and the channel
    if (fields(records, 0, "<u8") == first).all() and (fields(records, 3, "<u8") == second).all():
        return Records(records.raw, records.starts, step, uniform=True)
    return None


def tiles(raw: np.ndarray, indexes: list[bytes]) -> tuple[dict[int, Records], list[tuple[int, int]]]:
    """Each channel's message records in a decompressed chunk, and the gaps
    between them (where the other records, schemas and channels, are),
    checked to tile the chunk: no overlap, nothing outside it. Uniform runs
    count as one extent each (a few, walked in Python); anything else is
    checked record by record."""
    by_channel = indexed(raw, indexes)
    uniform = {cid: uniform_run(r, cid) for cid, r in by_channel.items()}
    if all(r is not None for r in uniform.values()):
        gaps, end = [], 0
        for first, last in sorted((int(r.starts[0]), int(r.starts[0]) + r.step * r.count) for r in uniform.values() if r):
            if first < end:
                raise Unsupported("overlapping message records")
            if first > end:
                gaps.append((end, first))
            end = last
        if end > raw.size:
            raise Unsupported("overlapping message records")
        return {cid: r for cid, r in uniform.items() if r}, [*gaps, (end, raw.size)] if end < raw.size else gaps
    starts = ascending(np.concatenate([r.starts for r in by_channel.values()]))
    every = Records(raw, starts, 0)
    if np.any(fields(every, 0, "u1") != Opcode.MESSAGE):
        raise Unsupported("message index points at something other than a message")
    ends = starts + 9 + fields(every, 1, "<u8").astype(np.int64)
    bounds = np.array([0, raw.size])  # the chunk's bounds as empty records
    starts, ends = np.concatenate((bounds[:1], starts, bounds[1:])), np.concatenate((bounds[:1], ends, bounds[1:]))
    if np.any(ends[:-1] > starts[1:]) or np.any(ends < starts):
        raise Unsupported("overlapping message records")
    gap = np.flatnonzero(ends[:-1] < starts[1:])
    return by_channel, list(zip(ends[gap].tolist(), starts[gap + 1].tolist()))
