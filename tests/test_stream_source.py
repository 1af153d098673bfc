"""Issue 16, item 1: a capture read chunk by chunk (``ingest.stream``).

The blocks, joined, must be the very samples ``load_dataset`` and
``repair_timebase`` give in memory (bit for bit, whatever the block and
batch sizes cut), the time-base findings the same, bad input refused with
the same one line, and the memory of a pass bounded by the block, not by
the capture."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal
from test_hostile_mcap import ACCELERATION, IMU, SMALL, TABLE, VELOCITY, _long_message, _set_float, rewrite

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest import load_dataset, mcap_fast, mcap_source
from rotcal.ingest.meta import load_meta
from rotcal.ingest.stream import COLUMNS, open_stream
from rotcal.simulate import SimulationSpec, simulate, write_dataset, write_mcap
from rotcal.simulate.streamed import write_streamed
from rotcal.timebase import repair_timebase

SPEC = SimulationSpec()
SPEC = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=2500, rates_hz=(0.05, 0.5)))  # 18,600 samples


@pytest.fixture
def small_batches(monkeypatch):
    """Batches of a few chunks, so that a capture is many batches."""
    monkeypatch.setattr(mcap_fast, "BATCH_BYTES", 100_000)


def in_memory(directory: Path):
    ds = load_dataset(directory)
    return ds, repair_timebase(ds.samples, ds.name)


def assert_streams_alike(directory: Path, block: int, bounded: bool = True) -> None:
    ds, tb = in_memory(directory)
    capture = open_stream(directory / "capture.mcap", ds.meta, block_samples=block)
    blocks = list(capture.blocks())
    assert capture.bounded == bounded
    assert len(blocks) == -(-ds.samples.height // block)  # one a block of samples read, rows dropped or not
    assert_frame_equal(pl.concat(blocks), tb.samples.select(COLUMNS))  # exact: values, order, types
    assert_frame_equal(pl.concat(list(capture.blocks())), tb.samples.select(COLUMNS))  # a second pass alike
    assert capture.n_samples == tb.samples.height
    assert_frame_equal(capture.timebase.findings_table(ds.name), tb.findings)
    assert capture.timebase.warnings == tb.warnings
    assert capture.timebase.unrepairable == tb.unrepairable.get("capture.mcap")
    assert (capture.notes, capture.label_source, capture.capture) == (ds.notes, "table", "capture.mcap")


@pytest.mark.parametrize("block", [777, 5000, 1 << 20])
def test_blocks_are_the_in_memory_samples(tmp_path, small_batches, block):
    """A clean capture (77 logging pauses between the plan's segments):
    blocks of 777 cut every segment and the table's 0.1 s ticks mid-way,
    batches of 100 kB every chunk run; one block holds the capture whole."""
    directory = write_streamed(SPEC, 7, tmp_path / "clean", "dut")
    assert_streams_alike(directory, block)


@pytest.mark.parametrize("defects", [
    "jitter_s=0.002,gap_count=3,drop_fraction=0.01",  # gaps and lost samples, jitter repaired on the grid
    "duplicate_fraction=0.01,repeat_stamp_fraction=0.01,jitter_s=0.001",  # records dropped, stamps placed
    "clock_drift_ppm=50,jitter_s=0.02",  # stamps out of order: read in memory
])
def test_captures_with_time_base_defects(tmp_path, small_batches, defects):
    spec = SPEC.with_timebase(defects)
    directory = write_dataset(simulate(spec, 3), spec, tmp_path / "defects", "mcap-cdr", "dut")
    assert_streams_alike(directory, 777, bounded="drift" not in defects)


def _refusal(read) -> str:
    with pytest.raises(InputError) as error:
        read()
    return str(error.value)


@pytest.mark.parametrize("patch", [
    _set_float(IMU, ACCELERATION, np.inf), _set_float(IMU, ACCELERATION, np.nan), _set_float(IMU, ACCELERATION, 1e300),
    _set_float(TABLE, VELOCITY, np.inf), _set_float(TABLE, VELOCITY, 1e300), _long_message,
], ids=["inf", "nan", "beyond", "table-inf", "table-beyond", "long-message"])
def test_bad_input_gives_the_in_memory_message(tmp_path, patch):
    """The hostile captures of tests/test_hostile_mcap.py: the same one line."""
    good = write_mcap(simulate(SMALL, 3), tmp_path / "good.mcap")
    bad = rewrite(good, tmp_path / "bad.mcap", patch)
    meta = load_meta(None)
    expected = _refusal(lambda: mcap_source.read_mcap_capture(bad, meta, None, Limits()))
    assert _refusal(lambda: open_stream(bad, meta)) == expected


def test_an_empty_file_and_a_missing_topic(tmp_path):
    meta = load_meta(None)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    assert _refusal(lambda: open_stream(empty, meta)) == f"{empty}: the file is empty"
    good = write_mcap(simulate(SMALL, 3), tmp_path / "good.mcap")
    other = replace(meta, imu_topic="/elsewhere", imu_topic_given=True)
    expected = _refusal(lambda: mcap_source.read_mcap_capture(good, other, None, Limits()))
    assert "'/elsewhere' is not in the file" in expected
    assert _refusal(lambda: open_stream(good, other)) == expected
