"""MCAP files that are valid but unusual, or damaged where the chunk pool is
busiest: empty chunks and chunks of definitions alone before the last one,
a damaged chunk while the next batch is in flight, one topic over several
channels. Every read runs in a subprocess with a timeout, so a deadlock in
the chunk pool fails the test instead of hanging the suite."""

from __future__ import annotations

import faulthandler
import json
import subprocess
import sys
from pathlib import Path

import pytest
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.records import Channel, Chunk, DataEnd, Footer, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap import messages as mcap_messages
from rotcal.ingest.formats.mcap import ros2_msgdefs
from rotcal.ingest.formats.mcap.writer import MAGIC

IMU_MESSAGES = 3000


def _record(record) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _imu_capture(path: Path) -> Path:
    """Imu messages in chunks of about 4 kB (many chunks, several batches once
    ``BATCH_BYTES`` is made small)."""
    with path.open("wb") as fh:
        writer = Ros2Writer(fh, chunk_size=4096, compression=CompressionType.ZSTD)
        imu = writer.register_msgdef(ros2_msgdefs.IMU_SCHEMA, ros2_msgdefs.IMU)
        for k in range(IMU_MESSAGES):
            t = 1_000_000_000 + 10_000_000 * k
            writer.write_message("/imu", imu, {
                "header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "imu"},
                "linear_acceleration": {"x": float(k), "y": 1.0, "z": 2.0}}, log_time=t, publish_time=t)
        writer.finish()
    return path


def _empty_chunk(compression: str) -> Chunk:
    data = zstandard.compress(b"") if compression == "zstd" else b""
    return Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0,
                 uncompressed_crc=0, uncompressed_size=0)


def _definitions_chunk() -> Chunk:
    body = (_record(Schema(id=77, name="other/msg/Thing", encoding="ros2msg", data=b"int32 a"))
            + _record(Channel(id=77, schema_id=77, topic="/other", message_encoding="cdr", metadata={})))
    return Chunk(compression="", data=body, message_start_time=0, message_end_time=0,
                 uncompressed_crc=0, uncompressed_size=len(body))


def _rebuilt(source: Path, path: Path, before_last: list[Chunk] = (), damaged: int | None = None) -> Path:
    """``source``'s records with ``before_last`` chunks inserted before its
    last chunk and the CRC of chunk ``damaged`` spoiled (no summary)."""
    records = list(StreamReader(source.open("rb"), emit_chunks=True).records)
    chunks = [k for k, r in enumerate(records) if isinstance(r, Chunk)]
    if damaged is not None:
        records[chunks[damaged]].uncompressed_crc ^= 1
    with path.open("wb") as fh:
        fh.write(MAGIC)
        for k, record in enumerate(records):
            if isinstance(record, DataEnd):
                fh.write(_record(record) + _record(Footer(0, 0, 0)) + MAGIC)
                break
            if k == chunks[-1]:
                fh.write(b"".join(map(_record, before_last)))
            fh.write(_record(record))
    return path


_READ = """
import json, sys
from pathlib import Path
from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap.records import Unsupported
mcap_fast.BATCH_BYTES = 64 * 1024  # many batches, each launched while the one before is decoded
out = {}
for workers in (1, 2, 3, 4):
    try:
        found = mcap_fast.read_topics(Path(sys.argv[1]), {"/imu"}, Limits(), workers)
        out[workers] = found["/imu"].count
    except Unsupported as exc:
        out[workers] = str(exc)
print(json.dumps(out))
"""


def _fast_reads(path: Path) -> dict[str, int | str]:
    """The fast path's reads on 1 to 4 threads, in a subprocess that a
    deadlock cannot hang (it fails at the timeout)."""
    done = subprocess.run([sys.executable, "-c", _READ, str(path)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    return _imu_capture(tmp_path_factory.mktemp("chunks") / "imu.mcap")


@pytest.mark.parametrize("inserted", [[_empty_chunk("")], [_empty_chunk("zstd")], [_definitions_chunk()],
                                      [_empty_chunk("zstd"), _definitions_chunk(), _empty_chunk("")]])
def test_empty_and_definition_only_chunks_read_in_full_on_any_thread_count(capture, tmp_path, inserted):
    path = _rebuilt(capture, tmp_path / "inserted.mcap", inserted)
    assert _fast_reads(path) == {str(w): IMU_MESSAGES for w in (1, 2, 3, 4)}
    assert mcap_messages.read_records(path, {"/imu"}, Limits())["/imu"].count == IMU_MESSAGES


@pytest.mark.parametrize("damaged", [0, 3, 20])
def test_a_damaged_chunk_while_the_next_batch_is_in_flight_is_declined_not_hung(capture, tmp_path, damaged):
    """A chunk failing its CRC in one batch while the next batch is queued
    behind it: the rest of its batch is cancelled, and the next batch's
    first chunk waits on one of them (a deadlock before every chunk's event
    was set as the read ends). Declined on every thread count, so that the
    per-message path words the error."""
    path = _rebuilt(capture, tmp_path / "damaged.mcap", [_empty_chunk("zstd")], damaged=damaged)
    reads = _fast_reads(path)
    assert all("fails its CRC check" in str(reads[str(w)]) for w in (1, 2, 3, 4)), reads



def _split_capture(path: Path, second_encoding: str = "cdr", second_first: bool = False) -> Path:
    """Imu messages on /imu alternating between two channels (a second
    channel of the same schema, or of JSON messages, registered after the
    Imu one or, ``second_first``, before it), in chunks of 4 kB."""
    with path.open("wb") as fh:
        ros2 = Ros2Writer(fh, chunk_size=4096, compression=CompressionType.ZSTD)
        raw, other = ros2._writer, None  # the same file: a second channel on the topic
        if second_first:
            other = raw.register_channel("/imu", second_encoding, 0)
        imu = ros2.register_msgdef(ros2_msgdefs.IMU_SCHEMA, ros2_msgdefs.IMU)
        for k in range(IMU_MESSAGES):
            t = 1_000_000_000 + 10_000_000 * k
            message = {"header": {"stamp": {"sec": t // 10**9, "nanosec": t % 10**9}, "frame_id": "imu"},
                       "linear_acceleration": {"x": float(k), "y": 1.0, "z": 2.0}}
            if other is None or k % 2 == 0:
                ros2.write_message("/imu", imu, message, log_time=t, publish_time=t)
                other = other or raw.register_channel("/imu", second_encoding, imu.id if second_encoding == "cdr" else 0)
            elif second_encoding == "cdr":
                raw.add_message(other, log_time=t, data=ros2._encoders[imu.id](message), publish_time=t)
            else:
                raw.add_message(other, log_time=t, publish_time=t,
                                data=json.dumps({"u": float(k), "v": 1.0, "w": 2.0}).encode())
        ros2.finish()
    return path


def test_a_topic_split_over_two_channels_of_one_schema_is_read_whole(tmp_path):
    """Only the first channel was read (half the samples, no note); both
    are now, on every thread count (the fast path leaves it to the
    per-message path), in time order."""
    from rotcal.ingest.formats.mcap import reader as mcap_source
    from rotcal.ingest.meta import load_meta

    path = _split_capture(tmp_path / "split.mcap")
    official = sum(1 for _ in __import__("mcap.reader", fromlist=["make_reader"]).make_reader(path.open("rb"))
                   .iter_messages(topics=["/imu"]))
    assert official == IMU_MESSAGES
    for workers in (1, 2, 3, 4):
        frame, _ = mcap_source.read_mcap_capture(path, load_meta(None), None, Limits(), workers)
        assert frame.height == IMU_MESSAGES and frame["t_ns"].is_sorted()
        assert frame["u"].to_list() == [float(k) for k in range(IMU_MESSAGES)]


def test_a_topic_split_over_channels_of_different_messages_is_refused_naming_both(tmp_path):
    """A JSON channel beside the Imu one on /imu: refused in one line that
    names both channels (before: the first channel read alone, "channel u
    holds 1e+06 in every sample" for a JSON channel registered first)."""
    from rotcal.ingest.formats.mcap import reader as mcap_source
    from rotcal.ingest.meta import load_meta

    path = _split_capture(tmp_path / "mixed.mcap", "json")
    with pytest.raises(InputError, match=r"topic '/imu' is split over channels of different messages: channel 1 "
                                         r"\(cdr, schema 'sensor_msgs/msg/Imu'\) and channel 2 \(json, schema None\)"):
        mcap_source.read_mcap_capture(path, load_meta(None), None, Limits())


def test_a_channel_record_repeated_keeps_the_fast_path(capture, tmp_path):
    """A writer may repeat a channel's record (same id) in later chunks: one
    channel, not a split topic, so the fast path reads it (declining sent a
    half-million-sample capture to the per-message path, 1.5 GB)."""
    from rotcal.ingest.formats.mcap import fast as mcap_fast

    channel = next(r for r in StreamReader(capture.open("rb")).records if isinstance(r, Channel) and r.topic == "/imu")
    body = _record(channel)
    repeated = Chunk(compression="", data=body, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                     uncompressed_size=len(body))
    path = _rebuilt(capture, tmp_path / "repeated.mcap", [repeated])
    assert mcap_fast.read_topics(path, {"/imu"}, Limits())["/imu"].count == IMU_MESSAGES  # decodes, does not decline


READERS = ["in memory", "block by block", "per message"]


def _read_all_ways(path: Path) -> dict[str, int | str]:
    """Each reader's rows (or its refusal) on 1 to 4 threads: the in-memory
    one (fast path, declining to the per-message one), the block reader
    of the streamed run (declining to the in-memory one), and the
    per-message reader alone."""
    from rotcal.ingest.formats.blocks import NotBlockwise
    from rotcal.ingest.formats.mcap import blocks as mcap_stream
    from rotcal.ingest.formats.mcap import reader as mcap_source
    from rotcal.ingest.meta import load_meta

    meta, out = load_meta(None), {}

    def attempt(name, read):
        try:
            out[name] = read()
        except InputError as exc:
            out[name] = str(exc).split(": ", 1)[1]

    def blockwise(workers):
        try:
            raw = mcap_stream.open_capture(path, meta, None, Limits(), workers, 1000, "c", None)
        except NotBlockwise:
            return mcap_source.read_mcap_capture(path, meta, None, Limits(), workers)[0].height
        return raw.whole.height if raw.whole is not None else sum(b.height for b in raw.blocks())

    faulthandler.dump_traceback_later(300, exit=True)  # a deadlock ends the run with every thread's stack, not a hang
    for workers in (1, 2, 3, 4):
        attempt(f"in memory {workers}", lambda w=workers: mcap_source.read_mcap_capture(path, meta, None, Limits(), w)[0].height)
        attempt(f"block by block {workers}", lambda w=workers: blockwise(w))
    topics = {meta.imu_topic, meta.table_topic}
    attempt("per message", lambda: mcap_source._capture(mcap_messages.read_records(path, topics, Limits()), path, meta,
                                                        None, 1, fast=False)[0].height)
    faulthandler.cancel_dump_traceback_later()
    return out


@pytest.mark.parametrize("recipe", ["split", "json first", "json second", "empty", "definitions", "all three"])
def test_every_mcap_recipe_reads_alike_on_every_path_and_thread_count(capture, tmp_path, recipe):
    """The issue's MCAP recipes through every reader: the whole topic (the
    official reader's 3,000 messages), or the one refusal naming both
    channels of a topic split over different messages; never half of it,
    a channel of the wrong messages, or a hang."""
    path = tmp_path / "recipe.mcap"
    if recipe in ("split", "json first", "json second"):
        _split_capture(path, "cdr" if recipe == "split" else "json", recipe == "json first")
    else:
        chunks = {"empty": [_empty_chunk("")], "definitions": [_definitions_chunk()],
                  "all three": [_empty_chunk(""), _definitions_chunk(), _empty_chunk("zstd")]}[recipe]
        _rebuilt(capture, path, chunks)
    reads = _read_all_ways(path)
    if recipe.startswith("json"):
        channels = ["channel 1 (json, schema None)", "channel 2 (cdr, schema 'sensor_msgs/msg/Imu')"]
        expected = (f"topic '/imu' is split over channels of different messages: "
                    f"{' and '.join(channels if recipe == 'json first' else [channels[1].replace('2', '1', 1), channels[0].replace('1', '2', 1)])}")
        assert all(str(v).startswith(expected) for v in reads.values()), reads
    else:
        assert set(reads.values()) == {IMU_MESSAGES}, reads
