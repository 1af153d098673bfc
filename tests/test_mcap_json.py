"""JSON messages on the vectorised MCAP path (``mcap_json.json_chunk``,
``json_frame``): each chunk parsed on its own thread, the chunks' fields
joined as the per-message path reads the whole channel."""

import threading
from pathlib import Path

import pytest
from mcap.writer import Writer
from polars.testing import assert_frame_equal

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest import mcap_fast, mcap_records, mcap_source
from rotcal.ingest.meta import load_meta

TOPICS = {"/imu", "/table/joint_states"}


def _capture(path: Path, imu_extra, table_axis=lambda k: "x") -> Path:
    """80 Imu messages and 8 table messages in chunks of about 1 kB (a
    dozen messages each); ``imu_extra(k)``: text added to message k."""
    with path.open("wb") as fh:
        writer = Writer(fh, chunk_size=1024)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        imu, table = writer.register_channel("/imu", "json", schema), writer.register_channel("/table/joint_states", "json", schema)
        for k in range(8):
            body = f'{{"t": {k * 0.1}, "axis": "{table_axis(k)}", "rate_hz": {k % 2 * 0.5}, "angle_deg": {k * 10.0}}}'
            writer.add_message(table, k, body.encode(), k)
        for k in range(80):
            writer.add_message(imu, 100 + k, f'{{"t": {k * 0.01}, "u": {k}, "v": 1.5, "w": -2{imu_extra(k)}}}'.encode(), 100 + k)
        writer.finish()
    return path


def _per_message(monkeypatch, path: Path):
    def decline(*args, **kwargs):
        raise mcap_records.Unsupported("forced")

    with monkeypatch.context() as m:
        m.setattr(mcap_fast, "read_topics", decline)
        return mcap_source.read_mcap_capture(path, load_meta(None), None, Limits())[0]


def _fast(path: Path):
    return mcap_source.read_mcap_capture(path, load_meta(None), None, Limits())[0]


def test_a_field_first_given_in_a_later_chunk_is_read_as_the_per_message_path_reads_it(tmp_path, monkeypatch):
    path = _capture(tmp_path / "late.mcap", lambda k: f', "temperature_c": {20 + k}' if k >= 50 else "")
    topics = mcap_fast.read_topics(path, TOPICS, Limits())  # does not decline
    assert len(topics["/imu"]._parts) == 0 and topics["/imu"].count == 80
    frame = _fast(path)
    assert frame["temperature_c"].to_list() == [None] * 50 + [20.0 + k for k in range(50, 80)]
    assert frame["u"].to_list() == [float(k) for k in range(80)]
    assert frame["angle_deg"][:10].to_list() == [0.0] * 10  # the first table message holds until t = 0.1 s
    assert_frame_equal(frame, _per_message(monkeypatch, path))
    assert not [t for t in threading.enumerate() if t.name.startswith("rotcal-json")]  # the parse threads are gone


def test_a_field_null_wherever_it_appears_in_one_chunk_falls_back(tmp_path, monkeypatch):
    path = _capture(tmp_path / "null.mcap", lambda k: ', "temperature_c": null' if k >= 70 else "")
    with pytest.raises(mcap_records.Unsupported, match="null in every message"):
        mcap_fast.read_topics(path, TOPICS, Limits())
    frame = _fast(path)
    assert frame["temperature_c"].null_count() == 80
    assert_frame_equal(frame, _per_message(monkeypatch, path))


@pytest.mark.parametrize(("extra", "table_axis", "message"), [
    (lambda k: ', "gx": NaN' if k == 66 else "", lambda k: "x", "'gx' of message 67 is not a finite number"),
    (lambda k: "", lambda k: "q" if k == 6 else "x", "unknown axis label 'q'"),
    (lambda k: ', "gx": "fast"' if k == 75 else "", lambda k: "x", "'gx' of message 76 is not a number"),
])
def test_bad_json_in_a_later_chunk_is_worded_by_the_per_message_path(tmp_path, monkeypatch, extra, table_axis, message):
    path = _capture(tmp_path / "bad.mcap", extra, table_axis)
    with pytest.raises(mcap_records.Unsupported):
        mcap_fast.read_topics(path, TOPICS, Limits())
    with pytest.raises(InputError, match=message) as fast_error:
        _fast(path)
    with pytest.raises(InputError) as slow_error:
        _per_message(monkeypatch, path)
    assert str(fast_error.value) == str(slow_error.value)
    assert "\n" not in str(fast_error.value)
