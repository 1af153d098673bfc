"""Hostile and damaged MCAP files (issue 17): every declared size checked
against what is there, chunk CRCs checked, chunks decompressed within a
memory budget, topics of another schema and non-finite values refused. Each
is a one-line error naming the file (exit 2) or the correct result, fast and
in bounded memory.

The files are the simulator's captures with bytes patched inside a chunk
(the chunk recompressed, its CRC recomputed unless the test keeps the old
one), or written by the ``mcap`` library's writer.
"""

from __future__ import annotations

import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.reader import StreamReader
from mcap.records import Chunk, DataEnd, Header
from mcap.writer import CompressionType, Writer
from polars.testing import assert_frame_equal

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap import reader as mcap_source
from rotcal.ingest.formats.mcap import records as mcap_records
from rotcal.ingest.formats.mcap import ros2_cdr, ros2_msgdefs
from rotcal.ingest.meta import load_meta
from rotcal.simulate import Plan, SimulationSpec, simulate, write_mcap

MAGIC = b"\x89MCAP0\r\n"
SMALL = SimulationSpec(plan=Plan(rotation_samples=300, step_samples=5))  # 3,960 samples, two chunks
TABLE, IMU = 1, 2  # the simulator's channel ids
ACCELERATION = 31 + ros2_cdr.imu_layout(len(b"dut\x00")).linear_acceleration  # u in an Imu message record
VELOCITY = 31 + ros2_cdr.joint_template("table", (2,), 1, 0)[1].velocity  # in a JointState message record


def read(path: Path, limits: Limits = Limits()):
    """The samples, without the column naming the file."""
    return mcap_source.read_mcap_capture(path, load_meta(None), None, limits)[0].drop("capture")


def refused(path: Path, *needles: str, limits: Limits = Limits()) -> str:
    with pytest.raises(InputError) as error:
        read(path, limits)
    message = str(error.value)
    assert "\n" not in message and message.startswith(str(path)), message
    for needle in needles:
        assert needle in message, message
    return message


def _record(record) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def rewrite(src: Path, dst: Path, patch=None, keep_crc: bool = False, insert: tuple = (None, 0, b"")) -> Path:
    """``src`` record by record, each chunk's records through ``patch(k,
    raw)`` and recompressed, and ``insert`` = (record type, n, bytes): the
    bytes before the n-th record of that type (counted from 0). The summary's
    offsets go stale (neither reader uses them)."""
    out, k, seen = [MAGIC], 0, 0
    with src.open("rb") as fh:
        for record in StreamReader(fh, emit_chunks=True).records:
            if insert[0] is not None and isinstance(record, insert[0]):
                out.append(insert[2] if seen == insert[1] else b"")
                seen += 1
            if isinstance(record, Chunk):
                raw = bytearray(zstandard.ZstdDecompressor().decompress(record.data, record.uncompressed_size))
                if patch is not None:
                    patch(k, raw)
                crc = record.uncompressed_crc if keep_crc else zlib.crc32(raw)
                record = Chunk(compression="zstd", data=zstandard.compress(bytes(raw)), uncompressed_crc=crc,
                               uncompressed_size=len(raw), message_start_time=record.message_start_time,
                               message_end_time=record.message_end_time)
                k += 1
            out.append(_record(record))
    dst.write_bytes(b"".join(out) + MAGIC)
    return dst


def messages(raw: bytearray, channel: int) -> list[int]:
    """Where each message record of ``channel`` starts in a chunk's records."""
    pos, found = 0, []
    while pos < len(raw):
        opcode, length = struct.unpack_from("<BQ", raw, pos)
        if opcode == 5 and struct.unpack_from("<H", raw, pos + 9)[0] == channel:
            found.append(pos)
        pos += 9 + length
    return found


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return write_mcap(simulate(SMALL, 3), tmp_path_factory.mktemp("hostile") / "capture.mcap")


def test_rewriting_alone_changes_no_sample(capture, tmp_path):
    assert_frame_equal(read(rewrite(capture, tmp_path / "same.mcap")), read(capture))


def _long_message(k, raw):
    """The length of a message in the first chunk set to 2^62."""
    if k == 0:
        at = messages(raw, IMU)[10]
        raw[at + 1 : at + 9] = struct.pack("<Q", 1 << 62)


def test_a_message_longer_than_its_chunk_is_refused_not_dropped(capture, tmp_path):
    """The per-message path read it as the rest of the chunk: its messages
    vanished as a logging pause."""
    refused(rewrite(capture, tmp_path / "long.mcap", _long_message), "corrupt MCAP: a record at byte",
            f"of the chunk at byte 70 declares {1 << 62} bytes where")


def _change_a_sample(k, raw):
    if k == 0:
        raw[messages(raw, IMU)[10] + ACCELERATION] ^= 1


def test_a_changed_byte_fails_the_chunk_crc(capture, tmp_path):
    refused(rewrite(capture, tmp_path / "changed.mcap", _change_a_sample, keep_crc=True),
            "corrupt MCAP: the chunk at byte 70 fails its CRC check")


def test_a_zero_crc_is_not_checked(capture, tmp_path):
    """The MCAP specification: an uncompressed_crc of zero means not computed."""
    path = rewrite(capture, tmp_path / "nocrc.mcap", _change_a_sample)
    data = bytearray(path.read_bytes())
    data[70 + 9 + 24 : 70 + 9 + 28] = bytes(4)  # the first chunk's uncompressed_crc (after its times and size)
    path.write_bytes(bytes(data))
    changed = read(path)
    assert changed.height == 3960 and not changed.equals(read(capture))


def test_a_chunk_whose_records_run_past_it_is_refused(capture, tmp_path):
    data = bytearray(capture.read_bytes())
    name_len = struct.unpack_from("<I", data, 70 + 9 + 28)[0]
    at = 70 + 9 + 32 + name_len  # the first chunk's records length
    data[at : at + 8] = struct.pack("<Q", struct.unpack_from("<Q", data, at)[0] + 1)
    path = tmp_path / "records.mcap"
    path.write_bytes(bytes(data))
    refused(path, "corrupt MCAP: the chunk at byte 70 declares", "bytes of records where it holds")


def test_a_non_imu_schema_on_the_dut_topic_is_refused_before_decoding(tmp_path):
    """A 1.3 kB file whose one 16 MB String message was decoded (2 GB, 20 s),
    then a traceback."""
    for name, definition, data in (
        ("std_msgs/msg/String", "string data", b"\x00\x01\x00\x00" + struct.pack("<I", 1 << 24) + b"a" * ((1 << 24) - 1) + b"\x00"),
        ("geometry_msgs/msg/Vector3", "float64 x\nfloat64 y\nfloat64 z", b"\x00\x01\x00\x00" + bytes(28)),
    ):
        path = tmp_path / f"{name.split('/')[-1]}.mcap"
        with path.open("wb") as fh:
            writer = Writer(fh, compression=CompressionType.ZSTD)
            writer.start("ros2", "hostile")
            channel = writer.register_channel("/imu", "cdr", writer.register_schema(name, "ros2msg", definition.encode()))
            writer.add_message(channel, 1, data, 1)
            writer.finish()
        assert path.stat().st_size < 4096
        # refused from the schema record, before the 16 MiB message is decoded
        refused(path, f"topic '/imu' has schema '{name}'; rotcal reads sensor_msgs/msg/Imu")


def test_a_table_topic_of_another_schema_is_refused(tmp_path):
    path = tmp_path / "table.mcap"
    imu = ros2_cdr.imu_template("dut")
    with path.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start("ros2", "hostile")
        dut = writer.register_channel("/imu", "cdr", writer.register_schema("sensor_msgs/msg/Imu", "ros2msg", ros2_msgdefs.IMU.encode()))
        table = writer.register_channel("/table/joint_states", "cdr",
                                        writer.register_schema("std_msgs/msg/String", "ros2msg", b"string data"))
        writer.add_message(table, 1, b"\x00\x01\x00\x00" + struct.pack("<I", 2) + b"x\x00", 1)
        for k in range(20):
            writer.add_message(dut, k + 1, imu.tobytes(), k + 1)
        writer.finish()
    refused(path, "topic '/table/joint_states' has schema 'std_msgs/msg/String'; rotcal reads sensor_msgs/msg/JointState")


def _peak_kib(path: Path, limit: int, workers: int) -> tuple[int, str]:
    """Peak resident memory of reading ``path`` in a fresh interpreter, over
    its peak after the imports (VmHWM: ru_maxrss would start from this
    process's peak); and the error it gave."""
    script = (
        "import sys\nfrom pathlib import Path\nfrom rotcal.config import Limits\nfrom rotcal.errors import InputError\n"
        "from rotcal.ingest.meta import load_meta\nfrom rotcal.ingest.formats.mcap.reader import read_mcap_capture\n"
        "def peak():\n    return int(next(x for x in open('/proc/self/status') if x.startswith('VmHWM')).split()[1])\n"
        "base = peak()\ntry:\n"
        f"    read_mcap_capture(Path(sys.argv[1]), load_meta(None), None, Limits(max_mcap_record_bytes={limit}), {workers})\n"
        "except InputError as exc:\n    print(exc)\n"
        "print(peak() - base)\n"
    )
    run = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, timeout=120, check=True)
    *message, growth = run.stdout.strip().splitlines()
    return int(growth), "\n".join(message)


def _mcap(*chunks: bytes) -> bytes:
    return MAGIC + _record(Header("", "hostile")) + b"".join(chunks) + b"\x02" + struct.pack("<QQQI", 20, 0, 0, 0) + MAGIC


def _zero_chunk(size: int, records: bytes = b"") -> bytes:
    """A chunk of ``records`` and zeros to ``size`` bytes, zstd-compressed."""
    raw = records + bytes(size - len(records))
    return _record(Chunk(compression="zstd", data=zstandard.compress(raw), uncompressed_crc=zlib.crc32(raw),
                         uncompressed_size=size, message_start_time=0, message_end_time=0))


def test_chunks_are_decompressed_within_a_memory_budget(tmp_path):
    """Sixteen chunks of 64 MiB, each one private record (which readers
    skip): they were decompressed all at once."""
    size = 64 << 20
    path = tmp_path / "big_chunks.mcap"
    path.write_bytes(_mcap(*[_zero_chunk(size, b"\x80" + struct.pack("<Q", size - 9))] * 16))
    growth, message = _peak_kib(path, size, workers=2)
    assert "topic '/imu' is not in the file (topics: none)" in message
    assert growth < (size + 2 * mcap_fast.BATCH_BYTES) // 1024, growth


def test_zeroed_chunks_are_refused_at_once(tmp_path):
    """Three all-zero chunks were walked nine bytes at a time in Python."""
    path = tmp_path / "zeros.mcap"
    path.write_bytes(_mcap(*[_zero_chunk(32 << 20)] * 3))
    # byte 0 of the first chunk: refused at the first record, not after walking the zeros
    refused(path, "corrupt MCAP: a record of opcode 0 at byte 0 of the chunk at byte")


@pytest.mark.parametrize("before", [(Chunk, 1), (DataEnd, 0)], ids=["after the first chunk", "after the last"])
def test_message_indexes_that_declare_more_than_they_hold_are_not_believed(capture, tmp_path, before):
    """64 of them asked for 128 GiB of columns; the per-message path, which
    reads no index, gives the samples."""
    bogus = (b"\x07" + struct.pack("<QHI", 6, IMU, 0xFFFFFFF0)) * 64
    path = rewrite(capture, tmp_path / "indexes.mcap", insert=(*before, bogus))
    assert_frame_equal(read(path), read(capture))


def test_too_many_definition_records_are_refused(tmp_path):
    """Channel-less schema records of 23 bytes: a 32 MiB chunk would be
    1.4 million Python calls."""
    schema = b"\x03" + struct.pack("<QHIII", 14, 1, 0, 0, 0)
    path = tmp_path / "schemas.mcap"
    path.write_bytes(_mcap(_zero_chunk(23 * 200_000, schema * 200_000)))
    # refused at the limit's count, before the other 100,000 records are walked
    refused(path, "more than 100000 schema, channel and other non-message records")


def _set_float(channel: int, offset: int, value: float):
    def patch(k, raw):
        if k == 0:
            raw[messages(raw, channel)[5] + offset : messages(raw, channel)[5] + offset + 8] = struct.pack("<d", value)
    return patch


@pytest.mark.parametrize("value", [np.inf, -np.inf, np.nan])
def test_a_non_finite_cdr_sample_is_refused(capture, tmp_path, value):
    refused(rewrite(capture, tmp_path / "inf.mcap", _set_float(IMU, ACCELERATION, value)), "'u' of message",
            f"is not a finite number ({value})")


def test_a_non_finite_table_velocity_is_refused(capture, tmp_path):
    refused(rewrite(capture, tmp_path / "table.mcap", _set_float(TABLE, VELOCITY, np.inf)),
            "table topic '/table/joint_states': the rate of message", "is not a finite number (-inf)")  # JOINT_SIGN


def _json_capture(path: Path, dut: list[str], table: list[str] = ()) -> Path:
    with path.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start("", "hostile")
        schema = writer.register_schema("s", "jsonschema", b"{}")
        imu, tab = writer.register_channel("/imu", "json", schema), writer.register_channel("/table/joint_states", "json", schema)
        for k, body in enumerate(table):
            writer.add_message(tab, k * 10**8, body.encode(), k * 10**8)
        for k, body in enumerate(dut):
            writer.add_message(imu, k * 10**7, body.encode(), k * 10**7)
        writer.finish()
    return path


def _samples(n: int = 50, **replace: str) -> list[str]:
    rows = [f'{{"t": {k * 0.01}, "u": {k}, "v": 1.5, "w": -2}}' for k in range(n)]
    for k, row in replace.items():
        rows[int(k[1:])] = row
    return rows


@pytest.mark.parametrize(("row", "problem"), [
    ('{"t": 0.07, "u": Infinity, "v": 1.5, "w": -2}', "'u' of message 8 is not a finite number (inf)"),
    ('{"t": 0.07, "u": 1e999, "v": 1.5, "w": -2}', "'u' of message 8 is not a finite number (inf)"),
    ('{"t": NaN, "u": 7, "v": 1.5, "w": -2}', "'t' of message 8 is not a finite number (nan)"),
    ('{"t": 1e300, "u": 7, "v": 1.5, "w": -2}', "'t' of message 8 is not a time in seconds (1e+300)"),
    ('{"t": "soon", "u": 7, "v": 1.5, "w": -2}', "'t' of message 8 is not a number ('soon')"),
    ('{"t": 0.07, "u": true, "v": 1.5, "w": -2}', "'u' of message 8 is not a number (True)"),
    ('{"t": 0.07, "u": 7, "v": 1.5, "w": -2, "axis": 3}', "'axis' of message 8 is not text"),
    ('[0.07, 7, 1.5, -2]', "message 8 is not a JSON object"),
])
def test_json_values_that_are_not_finite_numbers_are_refused(tmp_path, row, problem):
    refused(_json_capture(tmp_path / "dut.mcap", _samples(m7=row)), f"topic '/imu': {problem}")


@pytest.mark.parametrize(("row", "problem"), [
    ('{"t": NaN, "axis": "x", "rate_hz": 0.5, "angle_deg": 0}', "'t' of message 2 is not a finite number (nan)"),
    ('{"t": -1e15, "axis": "x", "rate_hz": 0.5, "angle_deg": 0}', "'t' of message 2 is not a time in seconds (-1e+15)"),
    ('{"t": 0.1, "axis": "x", "rate_hz": Infinity, "angle_deg": 0}', "'rate_hz' of message 2 is not a finite number (inf)"),
    ('{"t": 0.1, "axis": "q", "rate_hz": 0.5, "angle_deg": 0}', "unknown axis label 'q'"),
])
def test_json_table_values_that_are_not_finite_are_refused(tmp_path, row, problem):
    table = [f'{{"t": {k * 0.1}, "axis": "x", "rate_hz": 0.5, "angle_deg": {18 * k}}}' for k in range(5)]
    table[1] = row
    refused(_json_capture(tmp_path / "table.mcap", _samples(), table), "'/table/joint_states'", problem)


def test_good_json_captures_read_alike_on_both_paths(tmp_path, monkeypatch):
    table = [f'{{"t": {k * 0.1}, "axis": "x", "rate_hz": 0.5, "angle_deg": {18 * k}}}' for k in range(5)]
    path = _json_capture(tmp_path / "good.mcap", _samples(), table)
    fast = read(path)

    def decline(*args, **kwargs):
        raise mcap_source.Unsupported("forced")

    monkeypatch.setattr(mcap_fast, "read_topics", decline)
    assert_frame_equal(read(path), fast)
    assert fast["rate_hz"].drop_nulls().len() == 50


@pytest.mark.parametrize("kind", ["long", "crc", "json_t"])
def test_the_command_line_says_one_line_and_exits_2(capture, cli, tmp_path, kind):
    dataset = tmp_path / "dut"
    dataset.mkdir()
    if kind == "json_t":
        _json_capture(dataset / "capture.mcap", _samples(m3='{"t": NaN, "u": 7, "v": 1.5, "w": -2}'))
    else:
        rewrite(capture, dataset / "capture.mcap", _long_message if kind == "long" else _change_a_sample, keep_crc=kind == "crc")
    status, _, err = cli("run", dataset, "--out", tmp_path / "out")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and "capture.mcap" in lines[0] and "Traceback" not in err, (status, err)


def _message_into_next_chunk(k, raw):
    """The last record of the first chunk made 16 bytes longer than what
    remains of it: in the fast path's batch buffer the next chunk follows,
    so the record would read that chunk's first bytes as its own."""
    if k == 0:
        at = messages(raw, IMU)[-1]
        length = struct.unpack_from("<Q", raw, at + 1)[0]
        assert at + 9 + length == len(raw)  # the last record of the chunk
        raw[at + 1 : at + 9] = struct.pack("<Q", length + 16)


def test_a_message_running_into_the_next_chunk_is_refused(capture, tmp_path):
    """Both chunks are decompressed side by side into one buffer: a record
    may not span them (mcap_fast declines; the per-message path words it)."""
    path = rewrite(capture, tmp_path / "spanning.mcap", _message_into_next_chunk)
    with pytest.raises(mcap_records.Unsupported):
        mcap_fast.read_topics(path, {"/imu"}, Limits())
    refused(path, "corrupt MCAP: a record at byte", "of the chunk at byte 70 declares", "bytes where")


def _middle_message(field: str):
    """A patch of the middle Imu message of the second chunk: its channel id
    set to another channel's, or its opcode to a private record's. The
    message index still lists it among the evenly spaced Imu messages, so a
    check of the run's first and last records alone would pass it."""
    def patch(k, raw):
        if k == 1:
            found = messages(raw, IMU)
            at = found[len(found) // 2]
            if field == "channel":
                raw[at + 9 : at + 11] = struct.pack("<H", TABLE)
            else:
                raw[at] = 0x80
    return patch


@pytest.mark.parametrize("field", ["channel", "opcode"])
def test_every_record_of_an_even_run_is_checked(capture, tmp_path, field):
    path = rewrite(capture, tmp_path / f"{field}.mcap", _middle_message(field))
    with pytest.raises(mcap_records.Unsupported):
        mcap_fast.read_topics(path, {"/imu"}, Limits())
