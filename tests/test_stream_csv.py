"""A CSV capture read a block of lines at a time (``ingest.formats.csv.blocks``):
the blocks after the time base are the samples ``load_dataset`` and
``repair_timebase`` give in memory, bit for bit; what the block reader
does not take is read whole with the same values and messages; and a run
of a CSV capture read block by block gives the tables of the same samples
in MCAP read block by block, exactly."""

from __future__ import annotations

import io
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

import rotcal.run.stages as stages
from rotcal.blockwise.repaired import repaired_stream
from rotcal.config import Limits, RunConfig, with_options
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.formats.blocks import COLUMNS, NotBlockwise, open_stream
from rotcal.ingest.formats.csv import blocks as csv_stream
from rotcal.ingest.formats.csv.reader import read_csv_capture
from rotcal.ingest.meta import load_meta
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.timebase import repair_timebase

SPEC = SimulationSpec()
SPEC = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=2500, rates_hz=(0.05, 0.5)))  # 18,600 samples
HEADER = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg")


def as_csv(mcap_dataset: Path, directory: Path) -> Path:
    """The MCAP capture's samples (labels from its table channel) as one labelled CSV capture."""
    directory.mkdir()
    (directory / "dataset.toml").write_text((mcap_dataset / "dataset.toml").read_text())
    raw = open_stream(mcap_dataset / "capture.mcap", load_meta(mcap_dataset / "dataset.toml"))
    with open(directory / "capture.csv", "wb") as fh:
        for k, block in enumerate(raw.blocks()):
            block.with_columns(t=block["t_ns"] / 1e9).select(HEADER).write_csv(fh, include_header=k == 0)
    return directory


@pytest.fixture(scope="module", params=["", "duplicate_fraction=0.01,repeat_stamp_fraction=0.01,jitter_s=0.001"],
                ids=["clean", "duplicates"])
def csv_dataset(tmp_path_factory, request) -> Path:
    spec = SPEC.with_timebase(request.param) if request.param else SPEC
    root = tmp_path_factory.mktemp("csv")
    return as_csv(write_dataset(simulate(spec, 3), spec, root / "mcap", "mcap-cdr", "dut"), root / "csv")


@pytest.mark.parametrize("block", [777, 1 << 20])
@pytest.mark.parametrize("piece", [100, 1 << 18])
def test_blocks_are_the_in_memory_samples(csv_dataset, block, piece, monkeypatch):
    """Blocks of 777 lines cut every segment mid-way, parsed in pieces of
    100 lines (the last of each block 77); one block holds the capture whole."""
    monkeypatch.setattr(csv_stream, "PIECE_LINES", piece)
    ds = load_dataset(csv_dataset)
    memory = repair_timebase(ds.samples, ds.name)
    raw = open_stream(csv_dataset / "capture.csv", ds.meta, block_samples=block)
    assert raw.bounded and raw.n_samples == ds.samples.height
    heights = [b.height for b in raw.blocks()]  # before the time base drops any
    assert heights[:-1] == [block] * (len(heights) - 1) and 0 < heights[-1] <= block
    capture = repaired_stream(raw, block_samples=block)
    for _ in range(2):  # a later pass reads the same back
        blocks = list(capture.blocks())
        assert_frame_equal(pl.concat(blocks), memory.samples.select(COLUMNS))  # exact
    assert capture.n_samples == memory.samples.height
    assert capture.timebase.findings_table(ds.name).select("check", "detected", "action").equals(
        memory.findings.select("check", "detected", "action"))
    assert (capture.label_source, capture.notes) == ("file", ds.notes)


@pytest.mark.parametrize("change", ["nan", "backwards", "semicolons", "comment", "temperature"])
def test_what_the_block_reader_does_not_take(tmp_path, csv_dataset, change):
    """Bad values give the in-memory reader's one line; other layouts and
    columns are read whole, with the in-memory samples."""
    lines = (csv_dataset / "capture.csv").read_text().splitlines()
    if change == "nan":
        lines[3000] = lines[3000].replace(lines[3000].split(",")[1], "NaN", 1)
    elif change == "backwards":
        lines[5000], lines[5001] = lines[5001], lines[5000]
    elif change == "semicolons":
        lines = [line.replace(",", ";") for line in lines]
    elif change == "comment":
        lines.insert(1, "# logger 7")
    else:
        lines = [lines[0] + ",temperature_c", *(line + ",21.5" for line in lines[1:])]
    path = tmp_path / "capture.csv"
    path.write_text("\n".join(lines) + "\n")
    meta = load_meta(None)
    if change in ("nan", "backwards"):
        with pytest.raises(InputError) as memory:
            read_csv_capture(path, meta.csv_format, None, Limits())
        with pytest.raises(InputError) as streamed:
            open_stream(path, meta, block_samples=1000)
        assert str(streamed.value) == str(memory.value) and "row" in str(memory.value)
        return
    raw = open_stream(path, meta, block_samples=1000)
    assert not raw.bounded and raw.whole_because is not None
    assert raw.whole_because.startswith("a CSV capture its block reader does not take: ")
    assert_frame_equal(raw.whole, load_dataset(path).samples)


def test_a_streamed_csv_run_is_the_streamed_mcap_run(tmp_path, monkeypatch):
    """The run reads both captures block by block (``[run] stream_above_samples``
    below their size): the same samples give the same tables, bit for bit."""
    mcap = write_dataset(simulate(SPEC, 4), SPEC, tmp_path / "mcap", "mcap-cdr", "dut")
    csv = as_csv(mcap, tmp_path / "csv")
    config = with_options(RunConfig(), run={"stream_above_samples": 1000})
    streamed = []
    from_stream = stages._from_stream
    monkeypatch.setattr(stages, "_from_stream", lambda ds, s: streamed.append(ds.name) or from_stream(ds, s))
    outcomes = {name: run_dataset(path, tmp_path / f"out_{name}", config=config) for name, path in (("mcap", mcap), ("csv", csv))}
    assert streamed == ["mcap", "csv"]
    assert not any("read in memory" in n for o in outcomes.values() for n in o.notes)
    for table in ("fits", "intrinsic", "simultaneous", "uncertainty_budget"):
        a, b = (pl.read_parquet(tmp_path / f"out_{name}" / f"{table}.parquet").drop("dataset", "capture", "label_source", strict=False)
                for name in ("mcap", "csv"))
        assert_frame_equal(a, b)
    assert np.isfinite(pl.read_parquet(tmp_path / "out_csv" / "intrinsic.parquet")["value"].to_numpy()).all()


@pytest.mark.parametrize("read_bytes", [512, 1 << 24])
def test_a_long_line_is_not_held(tmp_path, csv_dataset, monkeypatch, read_bytes):
    """A line past ``[limits] max_line_bytes`` after many good ones: refused
    with the in-memory reader's one line, read 512 bytes at a time or more."""
    monkeypatch.setattr(csv_stream, "READ_BYTES", read_bytes)
    lines = (csv_dataset / "capture.csv").read_text().splitlines()
    lines.insert(4000, "1" * 5000)
    path = tmp_path / "capture.csv"
    path.write_text("\n".join(lines) + "\n")
    limits = Limits(max_line_bytes=1000)
    with pytest.raises(InputError) as memory:
        read_csv_capture(path, load_meta(None).csv_format, None, limits)
    with pytest.raises(InputError) as streamed:
        open_stream(path, load_meta(None), limits=limits, block_samples=1000)
    assert str(streamed.value) == str(memory.value) and "longer than the limit" in str(memory.value)


def test_the_block_reader_gives_up_a_long_line_at_the_limit(monkeypatch):
    """A line of 10 MB read 512 bytes at a time: given up once past the
    limit of 1000 bytes, not read whole."""
    monkeypatch.setattr(csv_stream, "READ_BYTES", 512)
    fh = io.BytesIO(b"1" * 10_000_000 + b"\n")
    with pytest.raises(NotBlockwise):
        list(csv_stream._line_blocks(fh, [100], 1000))
    assert fh.tell() <= 1000 + 512
