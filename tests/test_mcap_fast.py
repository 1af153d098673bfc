"""The vectorised MCAP path (``ingest.mcap_fast``) against the per-message
path, and the chunk-at-a-time writer against ``mcap_ros2``'s."""

from pathlib import Path

import numpy as np
import polars as pl
import pytest
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer
from polars.testing import assert_frame_equal

from rotcal.config import Limits
from rotcal.errors import InputError, LimitError
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap import reader as mcap_source
from rotcal.ingest.formats.mcap import records as mcap_records
from rotcal.ingest.formats.mcap import ros2_msgdefs
from rotcal.ingest.formats.mcap.writer import write_capture
from rotcal.ingest.meta import load_meta
from rotcal.model.physics import JOINT_SIGN
from rotcal.simulate import Plan, SimulationSpec, simulate, table_messages

from testdata import REAL

SMALL = SimulationSpec(plan=Plan(rotation_samples=300, step_samples=5))  # 3,960 samples, two 1 MiB chunks in CDR


def _per_message(monkeypatch, path: Path, meta=None):
    """The per-message path alone (the fast one made to decline)."""
    def decline(*args, **kwargs):
        raise mcap_records.Unsupported("forced")

    with monkeypatch.context() as m:
        m.setattr(mcap_fast, "read_topics", decline)
        return mcap_source.read_mcap_capture(path, meta or load_meta(None), None, Limits())


def _both(monkeypatch, path: Path, meta=None, fast_expected: bool = True):
    if fast_expected:
        mcap_fast.read_topics(path, {"/imu", "/table/joint_states"}, Limits())  # decodes, does not decline
    else:
        with pytest.raises(mcap_records.Unsupported):
            mcap_fast.read_topics(path, {"/imu", "/table/joint_states"}, Limits())
    fast = mcap_source.read_mcap_capture(path, meta or load_meta(None), None, Limits())
    slow = _per_message(monkeypatch, path, meta)
    assert_frame_equal(fast[0], slow[0])
    assert fast[1] == slow[1]
    return fast[0]


def _reference_cdr(samples: pl.DataFrame, table: pl.DataFrame, path: Path) -> None:
    """What the simulator wrote before: one mcap_ros2 call per message."""
    unknown = [-1.0] + [0.0] * 8
    stamp = lambda t: {"sec": int(t // 1_000_000_000), "nanosec": int(t % 1_000_000_000)}  # noqa: E731
    with path.open("wb") as fh:
        writer = Ros2Writer(fh, compression=CompressionType.ZSTD)
        imu = writer.register_msgdef("sensor_msgs/msg/Imu", ros2_msgdefs.IMU)
        joint = writer.register_msgdef("sensor_msgs/msg/JointState", ros2_msgdefs.JOINT_STATE)
        for t, axis, rate, angle in table.iter_rows():
            sign = JOINT_SIGN[axis]
            writer.write_message("/table/joint_states", joint, {
                "header": {"stamp": stamp(t), "frame_id": "table"}, "name": [axis],
                "position": [sign * np.deg2rad(angle)], "velocity": [sign * 2 * np.pi * rate], "effort": []},
                log_time=t, publish_time=t)
        for t, u, v, w in samples.select("t_ns", "u", "v", "w").iter_rows():
            writer.write_message("/imu", imu, {
                "header": {"stamp": stamp(t), "frame_id": "dut"},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "orientation_covariance": unknown,
                "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular_velocity_covariance": unknown,
                "linear_acceleration": {"x": u, "y": v, "z": w}, "linear_acceleration_covariance": [0.0] * 9},
                log_time=t, publish_time=t)
        writer.finish()


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    sim = simulate(SMALL, 3)
    directory = tmp_path_factory.mktemp("fast")
    table = table_messages(sim.samples)
    cdr = write_capture(sim.samples, table, directory / "cdr.mcap", "cdr")
    json_ = write_capture(sim.samples, table, directory / "json.mcap", "json")
    return sim, table, cdr, json_


def test_writer_is_byte_identical_to_mcap_ros2(small, tmp_path):
    sim, table, cdr, _ = small
    reference = tmp_path / "reference.mcap"
    _reference_cdr(sim.samples, table, reference)
    assert cdr.read_bytes() == reference.read_bytes()


def test_fast_path_equals_per_message_path_on_simulated_captures(small, monkeypatch):
    sim, _, cdr, json_ = small
    for path in (cdr, json_):
        frame = _both(monkeypatch, path)
        assert frame.height == sim.samples.height
        np.testing.assert_array_equal(frame["u"].to_numpy(), sim.samples["u"].to_numpy())
        assert frame["axis"].to_list() == sim.samples["axis"].to_list()


@pytest.mark.real
def test_fast_path_equals_per_message_path_on_the_real_jackal_file(monkeypatch):
    frame = _both(monkeypatch, REAL / "jackal_mcap" / "test2_ros2.mcap")
    assert frame.height == 3061


def _imu_file(path: Path, frame_ids: list[str], n_joints: int = 0, chunk_size: int = 1024 * 1024) -> Path:
    """Imu messages with the given frame ids (a varying length forces the
    per-message path) and optionally a 3-joint table."""
    rng = np.random.default_rng(5)
    with path.open("wb") as fh:
        writer = Ros2Writer(fh, chunk_size=chunk_size, compression=CompressionType.LZ4)
        imu = writer.register_msgdef("sensor_msgs/msg/Imu", ros2_msgdefs.IMU)
        joint = writer.register_msgdef("sensor_msgs/msg/JointState", ros2_msgdefs.JOINT_STATE)
        for k, frame_id in enumerate(frame_ids):
            t = 1_000_000_000 + 10_000_000 * k
            if n_joints and k % 3 == 0:
                moving = k // 30 % 4  # a joint turns, then all rest with one moved, then hold
                velocity = [0.0] * n_joints
                if moving < n_joints:
                    velocity[moving] = 0.5
                position = [0.1 * (k // 60), 0.2, 0.3 + (k // 45) * 0.01]
                writer.write_message("/table/joint_states", joint, {
                    "header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "t"},
                    "name": ["x", "y", "z"], "position": position, "velocity": velocity, "effort": []},
                    log_time=t, publish_time=t)
            acc = rng.normal(0, 1, 3)
            writer.write_message("/imu", imu, {
                "header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": frame_id},
                "linear_acceleration": {"x": acc[0], "y": acc[1], "z": acc[2]}}, log_time=t, publish_time=t)
        writer.finish()
    return path


def test_three_joint_table_and_lz4_chunks_decode_alike(tmp_path, monkeypatch):
    frame = _both(monkeypatch, _imu_file(tmp_path / "joints.mcap", ["imu"] * 600, n_joints=3))
    assert set(frame["axis"].drop_nulls()) == {"x", "y", "z"}


@pytest.mark.parametrize("workers", [1, 2, 3])
def test_many_chunks_on_several_threads_decode_alike(tmp_path, monkeypatch, workers):
    """Chunks of a few kilobytes, both channels in each (records checked one
    by one), decoded in file order and copied into their rows side by side
    on the pool's threads: the per-message path's samples, row for row."""
    path = _imu_file(tmp_path / "chunks.mcap", ["imu"] * 3000, n_joints=3, chunk_size=4096)
    monkeypatch.setattr(mcap_fast, "BATCH_BYTES", 64 * 1024)  # several batches in flight, one after the other
    found = mcap_fast.read_topics(path, {"/imu"}, Limits(), workers)  # decodes, does not decline
    assert found["/imu"].count == 3000 and found["/table/joint_states"].count == 1000
    with monkeypatch.context() as m:
        m.setattr(mcap_source, "read_records", None)  # no fallback: the samples are the fast path's
        fast = mcap_source.read_mcap_capture(path, load_meta(None), None, Limits(), workers)
    assert_frame_equal(fast[0], _per_message(monkeypatch, path, None)[0])
    assert fast[0].height == 3000 and fast[0]["t_ns"].is_sorted()


def test_unknown_layout_falls_back_with_identical_samples(tmp_path, monkeypatch):
    frame = _both(monkeypatch, _imu_file(tmp_path / "mixed.mcap", ["a", "base_link"] * 50), fast_expected=False)
    assert frame.height == 100


def test_json_message_spanning_lines_falls_back(tmp_path, monkeypatch):
    from mcap.writer import Writer

    path = tmp_path / "pretty.mcap"
    with path.open("wb") as fh:
        writer = Writer(fh)
        writer.start()
        channel = writer.register_channel("/imu", "json", writer.register_schema("s", "jsonschema", b"{}"))
        for k in range(20):
            body = f'{{"t": {k * 0.01},\n "u": {k}, "v": 1.5, "w": -2}}' if k == 7 else f'{{"t": {k * 0.01}, "u": {k}, "v": 1.5, "w": -2}}'
            writer.add_message(channel, k, body.encode(), k)
        writer.finish()
    assert _both(monkeypatch, path, fast_expected=False).height == 20


def test_damaged_files_are_refused_as_before(small, tmp_path, monkeypatch):
    _, _, cdr, _ = small
    data = cdr.read_bytes()
    truncated = tmp_path / "truncated.mcap"
    truncated.write_bytes(data[:-4000])  # ends inside the summary
    corrupt = tmp_path / "corrupt.mcap"
    corrupt.write_bytes(b"not an mcap" + data[11:])
    for path in (truncated, corrupt):
        with pytest.raises(InputError, match="(truncated|corrupt) MCAP") as fast_error:
            mcap_source.read_mcap_capture(path, load_meta(None), None, Limits())
        with pytest.raises(InputError) as slow_error:
            _per_message(monkeypatch, path)
        assert str(fast_error.value) == str(slow_error.value)
        assert "\n" not in str(fast_error.value)
    with pytest.raises(LimitError, match="larger than the limit of 1024 bytes"):
        mcap_source.read_mcap_capture(cdr, load_meta(None), None, Limits(max_mcap_record_bytes=1024))


@pytest.mark.parametrize(("extra", "fast_expected", "labelled"), [
    ("", True, True),  # the table's labels
    (', "note": {"deep": [1, "x"]}', True, True),  # a key not read, of any kind
    (', "axis": null', False, False),  # a key null everywhere is a column of nulls: the table is not read
    (', "axis": "X"', False, True),  # a label the parser cannot check: read as text and lowercased
])
def test_json_fields_read_alike_on_both_paths(tmp_path, monkeypatch, extra, fast_expected, labelled):
    from mcap.writer import Writer

    path = tmp_path / "fields.mcap"
    with path.open("wb") as fh:
        writer = Writer(fh)
        writer.start()
        schema = writer.register_schema("s", "jsonschema", b"{}")
        imu, table = writer.register_channel("/imu", "json", schema), writer.register_channel("/table/joint_states", "json", schema)
        writer.add_message(table, 0, b'{"t": 0, "axis": "x", "rate_hz": 0.5, "angle_deg": 0}', 0)
        for k in range(20):
            writer.add_message(imu, k, f'{{"t": {k * 0.01}, "u": {k}, "v": 1.5, "w": -2{extra}}}'.encode(), k)
        writer.finish()
    frame = _both(monkeypatch, path, fast_expected=fast_expected)
    assert frame["u"].to_list() == [float(k) for k in range(20)]
    assert frame["axis"].to_list() == (["x"] * 20 if labelled else [None] * 20)
    assert frame["rate_hz"].to_list() == ([0.5] * 20 if labelled and not extra.startswith(', "axis"') else [None] * 20)
