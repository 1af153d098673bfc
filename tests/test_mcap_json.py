"""The JSON-lines reading of MCAP JSON messages (``ingest.mcap_json``) and
the JSON branch of the table channel (``ingest.mcap_table``), on
hand-built records whose lines, colons and values are counted by hand."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
import pytest

from rotcal.errors import InputError
from rotcal.ingest.formats.mcap.json_lines import json_lines, parse_json_lines
from rotcal.ingest.formats.mcap.records import Unsupported
from rotcal.ingest.formats.mcap.table import _json_track, json_time_ns

HEADER = 31  # an MCAP message record's header: opcode, length, channel, sequence, two times


def _chunk(messages: list[bytes], foreign_after: int = -1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A decompressed chunk of message records (headers of 0xff bytes, which
    hold colons and newlines: 0x3a and 0x0a would do as well), one foreign
    record of 40 bytes after message ``foreign_after``; the messages' data
    offsets and sizes."""
    raw, data = bytearray(), []
    for k, message in enumerate(messages):
        raw += b"\x3a\x0a" + b"\xff" * (HEADER - 2)
        data.append(len(raw))
        raw += message
        if k == foreign_after:
            raw += b"\x0a\x3a" * 20
    return np.frombuffer(bytes(raw), np.uint8).copy(), np.array(data), np.array([len(m) for m in messages])


@pytest.mark.parametrize("foreign_after", [-1, 0])
def test_json_lines_cuts_messages_and_counts_their_colons(foreign_after):
    messages = [b'{"t": 1, "u": 2}', b'{"a":{"b":3}}', b"[4]"]
    raw, data, sizes = _chunk(messages, foreign_after)
    text, colons = json_lines(raw, data, sizes)
    assert text == b'{"t": 1, "u": 2}\n{"a":{"b":3}}\n[4]'
    assert colons == 4  # 2 + 2 + 0, none of the headers' or the foreign record's


def test_json_lines_refuses_a_message_spanning_lines():
    raw, data, sizes = _chunk([b'{"t": 1}', b'{"t":\n2}'])
    with pytest.raises(Unsupported, match="line break"):
        json_lines(raw, data, sizes)


def test_parse_json_lines_reads_every_chunk_as_one_frame():
    parts = [b'{"t": 0.5, "u": 1}\n{"t": 1.5, "u": -2}', b'{"t": 2.5, "u": 3, "w": 4}']
    frame = parse_json_lines(parts, 3, colons=7)
    assert frame.columns == ["t", "u", "w"]  # "w" first given in the second chunk: null before
    assert frame.rows() == [(0.5, 1.0, None), (1.5, -2.0, None), (2.5, 3.0, 4.0)]
    # the first message's fields only, when the colons say no message has another key
    assert parse_json_lines(parts[:1], 2, colons=4).rows() == [(0.5, 1.0), (1.5, -2.0)]


@pytest.mark.parametrize(("parts", "n", "problem"), [
    ([b'{"t": 0.5, "u": 1}', b'{"t": 1.5, "u": 2, "w": null}'], 2, "null in every message"),
    ([b'{"t": 0.5, "axis": "x"}', b'{"t": 1.5, "axis": "X"}'], 2, "axis label"),
    ([b'{"t": 0.5}', b'{"t": 1.5'], 2, "cannot parse"),
    ([b'{"t": 0.5}', b'{"t": 1.5}\n'], 3, "one object a line"),
])
def test_parse_json_lines_leaves_to_the_per_message_path(parts, n, problem):
    colons = sum(part.count(b":") for part in parts)
    with pytest.raises(Unsupported, match=problem):
        parse_json_lines(parts, n, colons)


def test_json_times_round_to_nanoseconds_or_take_the_log_time():
    log_ns = np.array([7, 8, 9])
    # 0.06 s * 1e9 is 60000000.00000001 in binary: rounded to 60000000 ns; -1.25e-9 s rounds half to even
    assert json_time_ns(np.array([0.06, 2.5e-9, -1.25e-9]), log_ns, "/imu", Path("c.mcap")).tolist() == [60_000_000, 2, -1]
    assert json_time_ns(np.array([0.06, np.nan, 3.0]), log_ns, "/imu", Path("c.mcap")).tolist() == [60_000_000, 8, 3_000_000_000]
    with pytest.raises(InputError, match=r"'t' of message 2 is not a time in seconds \(-1e\+10\)"):
        json_time_ns(np.array([0.0, -1e10, np.nan]), log_ns, "/imu", Path("c.mcap"))


def test_json_table_axis_codes_and_unknown_labels():
    frame = pl.DataFrame({"t": [0.0, 1.0, 2.0], "axis": ["z", "x", "y"], "rate_hz": [0.5, 0.0, 1.0], "angle_deg": [0.0, 10.0, 20.0]})
    track = _json_track(frame, np.zeros(3, np.int64), "/table", Path("c.mcap"))
    assert track.axis.tolist() == [2, 0, 1] and track.axis.dtype == np.int8
    for labels, shown in ((["x", "q", None], "'q'"), (["x", "y", None], "None")):
        with pytest.raises(InputError, match=f"unknown axis label {shown}"):
            _json_track(frame.with_columns(axis=pl.Series(labels, dtype=pl.String)), np.zeros(3, np.int64), "/table", Path("c.mcap"))
    with pytest.raises(InputError, match="unknown axis label None"):
        _json_track(frame.drop("axis"), np.zeros(3, np.int64), "/table", Path("c.mcap"))
