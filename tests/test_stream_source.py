"""A capture read chunk by chunk (``ingest.formats.blocks``, ``ingest.formats.mcap.blocks``)
and repaired block by block (``blockwise.repaired``).

The blocks, joined, must be the very samples ``load_dataset`` and
``repair_timebase`` give in memory (bit for bit, whatever the block and
batch sizes cut), the time-base findings the same, bad input refused with
the same one line, and the memory of a pass bounded by the block, not by
the capture."""

from __future__ import annotations

import re
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal
from test_hostile_mcap import ACCELERATION, IMU, SMALL, TABLE, VELOCITY, _long_message, _set_float, rewrite

from rotcal.blockwise import grid as stream_grid
from rotcal.blockwise import ranks as stream_ranks
from rotcal.blockwise import repaired as timebase_blocks
from rotcal.blockwise.repaired import repaired_stream
from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.formats.blocks import COLUMNS, open_stream
from rotcal.ingest.formats.mcap import blocks as stream
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap import reader as mcap_source
from rotcal.ingest.meta import load_meta
from rotcal.ingest.spill import Spill, replayed
from rotcal.simulate import SimulationSpec, simulate, write_dataset, write_mcap
from rotcal.simulate.blocks import write_streamed
from rotcal.timebase import repair_timebase
from rotcal.timebase.check import check_capture

SPEC = SimulationSpec()
SPEC = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=2500, rates_hz=(0.05, 0.5)))  # 18,600 samples


@pytest.fixture(params=["histograms", "held"])
def small_batches(monkeypatch, request):
    """Batches of a few chunks and stamps read back 1000 at a time, so that
    a capture is many batches and its time base many blocks; the time
    base's medians narrowed by histograms over passes (as for captures
    past ``stream_ranks.HELD``), or picked among the values held."""
    monkeypatch.setattr(mcap_fast, "BATCH_BYTES", 100_000)
    monkeypatch.setattr(stream, "_STAMP_BLOCK", 1000)
    if request.param == "histograms":
        monkeypatch.setattr(stream_ranks, "HELD", 1000)


def streamed_capture(path: Path, meta, block_samples: int = 1 << 20):
    """The capture's blocks after the time base, as the streamed run reads them."""
    return repaired_stream(open_stream(path, meta, block_samples=block_samples), block_samples=block_samples)


NUMBER = re.compile(r"-?\d+(\.\d+)?(e[-+]?\d+)?")


def assert_findings_alike(streamed: pl.DataFrame, memory: pl.DataFrame) -> None:
    """The same checks, detections and actions; values and the numbers in
    the evidence equal to rounding: the streamed sums add the cross
    products in another order (the means and medians are exact), so the
    period differs in its last bits, and residuals at the level of rounding
    (1e-13 s) with it."""
    assert_frame_equal(streamed.drop("value", "std_uncertainty", "evidence"), memory.drop("value", "std_uncertainty", "evidence"))
    for column in ("value", "std_uncertainty"):
        assert np.allclose(streamed[column].fill_null(0).to_numpy(), memory[column].fill_null(0).to_numpy(), rtol=1e-9, atol=1e-12)
    for a, b in zip(streamed["evidence"], memory["evidence"]):
        assert NUMBER.sub("#", a) == NUMBER.sub("#", b)
        x, y = (np.array([float(m.group()) for m in NUMBER.finditer(e)]) for e in (a, b))
        assert np.allclose(x, y, rtol=5e-3, atol=1e-9), (a, b)  # 3 significant digits; ms at rounding


def in_memory(directory: Path):
    ds = load_dataset(directory)
    return ds, repair_timebase(ds.samples, ds.name)


def assert_streams_alike(directory: Path, block: int, bounded: bool = True, grid_streamed: bool = True) -> None:
    """``grid_streamed``: the time base checked without the stamps in memory (no repeated stamps)."""
    ds, tb = in_memory(directory)
    held = []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(timebase_blocks, "check_capture", lambda *a, **k: held.append(1) or check_capture(*a, **k))
        capture = streamed_capture(directory / "capture.mcap", ds.meta, block_samples=block)
    assert bool(held) != grid_streamed
    blocks = list(capture.blocks())
    assert capture.bounded == bounded
    assert len(blocks) == -(-ds.samples.height // block)  # one a block of samples read, rows dropped or not
    joined, memory = pl.concat(blocks), tb.samples.select(COLUMNS)
    if any("placed on the regular" in w for w in tb.warnings):
        # stamps replaced by the fitted grid, a + T k: a period differing in its last bit (the cross
        # products summed in another order) moves a stamp by 1 ns where a + T k is near a half
        step = np.abs(joined["t_ns"].to_numpy() - memory["t_ns"].to_numpy())
        assert step.max() <= 1 and np.mean(step) < 1e-3
        joined, memory = joined.drop("t_ns"), memory.drop("t_ns")
    assert_frame_equal(joined, memory)  # exact: values, order, types
    assert_frame_equal(pl.concat(list(capture.blocks())).select(joined.columns), memory)  # a second pass alike
    assert capture.n_samples == tb.samples.height
    assert_findings_alike(capture.timebase.findings_table(ds.name), tb.findings)
    assert [NUMBER.sub("#", w) for w in capture.timebase.warnings] == [NUMBER.sub("#", w) for w in tb.warnings]
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
    assert_streams_alike(directory, 777, bounded="drift" not in defects, grid_streamed="jitter_s=0.002" in defects)


def _stamps(seed: int, n: int, jitter_ns: float = 0.0, drift_ppm: float = 0.0, drop: float = 0.0, pauses: int = 0,
            slip: bool = False) -> np.ndarray:
    """A logger's stamps at 1 kHz (epoch nanoseconds): white jitter, a clock
    running ``drift_ppm`` fast, lost samples, and pauses of 50 to 500 slots
    after which the grid's phase holds or (``slip``) moves by a fraction of a slot."""
    rng = np.random.default_rng(seed)
    k = np.arange(n, dtype=float)
    for a in np.sort(rng.choice(np.arange(1, n), pauses, replace=False)):
        k[a:] += rng.integers(50, 500) + (rng.uniform(0.2, 0.8) if slip else 0.0)
    t = np.rint(k * 1e6 * (1 + drift_ppm * 1e-6) + rng.normal(0.0, jitter_ns, n)).astype(np.int64)
    return 1_700_000_000_000_000_000 + t[rng.random(n) >= drop]  # whole ns past the epoch (a float's step: 256 ns)


@pytest.mark.parametrize("block", [777, 1 << 16])
@pytest.mark.parametrize("held", [True, False])
@pytest.mark.parametrize("defects", [
    {},  # the slots counted from the intervals are the fitted grid's at once
    {"jitter_ns": 2e4},
    {"drift_ppm": 300, "drop": 0.02, "pauses": 5},  # runs joined at each lost sample; three re-slotting passes
    {"pauses": 20, "slip": True, "drop": 0.01, "jitter_ns": 1e4},  # runs joined, then the fixed point
    {"pauses": 20, "drop": 0.05, "jitter_ns": 5e4},
])
def test_the_time_base_from_blocks_is_the_in_memory_one(monkeypatch, block, held, defects):
    """``stream_grid`` against ``check_capture`` on the same stamps: the
    same findings (values to rounding), missing slots, gaps and pauses,
    whatever the blocks cut (many runs a block, or one)."""
    if not held:
        monkeypatch.setattr(stream_ranks, "HELD", 1000)
    t = _stamps(1, 200_000, **defects)
    streamed = stream_grid.stream_grid(lambda: (t[a : a + block].copy() for a in range(0, t.size, block)), t.size, "c")
    memory = check_capture(t, [np.zeros(t.size)] * 3, "c")
    assert streamed is not None and memory.gaps is not None and streamed.gaps is not None
    truth = 1e-3 * (1 + defects.get("drift_ppm", 0) * 1e-6)
    # the simulated clock, within the noise and the float's step at the epoch (256 ns) over the span
    assert abs(streamed.interval_s / truth - 1) < 4 * streamed.findings[0].std_uncertainty / truth + 256 / (t[-1] - t[0])
    for a, b in zip(streamed.findings, memory.findings, strict=True):
        assert (a.check, a.detected, a.action) == (b.check, b.detected, b.action)
        assert np.isclose(a.value, b.value, rtol=1e-9, atol=1e-12), (a, b)
    g, h = streamed.gaps, memory.gaps
    assert (g.missing, g.slots, g.phase_pauses) == (h.missing, h.slots, h.phase_pauses)
    np.testing.assert_array_equal(g.length, h.length)
    np.testing.assert_allclose(g.middle_ns, h.middle_ns, rtol=0, atol=1.0)


@pytest.mark.parametrize("room", [True, False])
def test_the_capture_is_decoded_once(tmp_path, monkeypatch, room):
    """The first pass keeps the decoded samples and table messages on disk:
    the chunks are read once however many passes follow (three here), and
    the passes give the in-memory samples. With too little free disk the
    capture is decoded again on each pass (two readers: the DUT's channel
    and the table's), with a note, and gives the same samples."""
    directory = write_streamed(SPEC, 7, tmp_path / "clean", "dut")
    ds, tb = in_memory(directory)
    monkeypatch.setattr(stream, "room_for", lambda size: room)
    reads = []
    original = mcap_fast.iter_topic_batches
    monkeypatch.setattr(mcap_fast, "iter_topic_batches", lambda *a, **k: reads.append(1) or original(*a, **k))
    capture = streamed_capture(directory / "capture.mcap", ds.meta, block_samples=5000)
    for _ in range(3):
        assert_frame_equal(pl.concat(list(capture.blocks())), tb.samples.select(COLUMNS))
    assert len(reads) == (1 if room else 1 + 3 * 2)
    assert (stream.SPILL_NOTE in capture.notes) == (not room)
    assert tuple(n for n in capture.notes if n != stream.SPILL_NOTE) == ds.notes


def test_a_spill_gives_back_what_was_written():
    """Batches of any length (none too), read back in pieces of any length: the same values, in order."""
    rng = np.random.default_rng(4)
    spill = Spill({"t_ns": np.int64, "axis": np.int8, "x": np.float64})
    sizes = [0, 1, 999, 0, 4096, 17]
    written = {"t_ns": rng.integers(-2**62, 2**62, sum(sizes)), "axis": rng.integers(-1, 3, sum(sizes)).astype(np.int8),
               "x": rng.normal(size=sum(sizes))}
    cuts = np.cumsum([0, *sizes])
    for a, b in zip(cuts[:-1], cuts[1:]):
        spill.append({k: v[a:b] for k, v in written.items()})
    assert spill.rows == sum(sizes)
    for rows in (1, 7, 1000, 1 << 20):
        pieces = list(spill.pieces(rows))
        assert [p["x"].size for p in pieces[:-1]] == [rows] * (len(pieces) - 1) and 0 < pieces[-1]["x"].size <= rows
        for k, v in written.items():
            read = np.concatenate([p[k] for p in pieces])
            assert read.dtype == v.dtype and np.array_equal(read, v), k
    assert [list(p) for p in spill.pieces(4096, ("x",))] == [["x"], ["x"]]
    spill.close()


AXES3 = pl.Enum(["x", "y", "z"])
FRAMES = [pl.DataFrame({"t_ns": [1, 2, 3], "axis": pl.Series(["x", None, "z"], dtype=AXES3), "rate_hz": [0.5, -1.0, 2.0]}),
          pl.DataFrame({"t_ns": [4], "axis": pl.Series(["y"], dtype=AXES3), "rate_hz": [np.nan]}),
          pl.DataFrame(schema={"t_ns": pl.Int64(), "axis": AXES3, "rate_hz": pl.Float64()})]


@pytest.mark.parametrize("keeps", [True, False])
def test_labels_are_kept_by_the_first_whole_pass_and_read_back(keeps):
    """``spill.replayed``: a pass left off keeps nothing, the first whole
    pass keeps the labels (Enum nulls and all), the later passes give them
    back beside the other columns without reading again; a null number is
    not kept: read again."""
    frames = FRAMES if keeps else [FRAMES[0], FRAMES[1].with_columns(rate_hz=None)]
    reads, kept = [], []
    passes = replayed(lambda: reads.append(1) or iter(frames), {"axis": AXES3, "rate_hz": pl.Float64()}, 4,
                      lambda: (f.select("t_ns") for f in frames), lambda: kept.append(1))
    next(passes())  # a pass left off
    for _ in range(3):
        for ours, theirs in zip(passes(), frames, strict=True):
            assert_frame_equal(ours, theirs)
    assert (len(reads), len(kept)) == ((2, 1) if keeps else (4, 0))


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


MEMORY_CHILD = """
import sys
from pathlib import Path
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap import blocks as stream
from rotcal.ingest.meta import load_meta
from rotcal.ingest.formats.blocks import open_stream
from rotcal.blockwise import ranks as stream_ranks
from rotcal.timebase import repair_timebase
from rotcal.blockwise.repaired import repaired_stream

def status(key):
    return int(next(line for line in open("/proc/self/status") if line.startswith(key)).split()[1])

directory = Path(sys.argv[1])
open("/proc/self/clear_refs", "w").write("5")  # the peak (VmHWM) counted from here
base = status("VmRSS")
if sys.argv[2] == "memory":
    ds = load_dataset(directory)
    n = repair_timebase(ds.samples, ds.name).samples.height
else:
    # small batches and blocks: the part of the memory that does not grow with the capture
    mcap_fast.BATCH_BYTES, stream._STAMP_BLOCK, stream_ranks.GATHER = 1 << 20, 1 << 14, 1 << 15
    raw = open_stream(directory / "capture.mcap", load_meta(directory / "dataset.toml"), block_samples=1 << 14)
    capture = repaired_stream(raw, block_samples=1 << 14)
    n = sum(block.height for block in capture.blocks())
print(n, status("VmHWM") - base)
"""


def test_a_pass_holds_a_block_not_the_capture(tmp_path):
    """Half a million samples (46 MB as a sample table): the streamed
    reader's peak growth (first pass, time base, a pass of blocks of 16,384
    samples, batches of 512 kB) is a small part of the in-memory reader's,
    each measured in a process of its own from the resident memory after
    the imports."""
    spec = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=80_000))
    directory = write_streamed(spec, 7, tmp_path / "long", "dut")

    def peak(part: str) -> tuple[int, int]:
        out = subprocess.run([sys.executable, "-c", MEMORY_CHILD, str(directory), part], capture_output=True, text=True,
                             check=True).stdout.split()
        return int(out[0]), int(out[1])
    (n_memory, memory), (n_streamed, streamed) = peak("memory"), peak("stream")
    assert n_memory == n_streamed > 400_000
    assert memory > 95 * n_memory / 1024  # kB: the sample table at least
    print(f"peak growth: streamed {streamed} kB, in memory {memory} kB")
    assert streamed < 0.4 * memory, (streamed, memory)  # measured 27 MB against 83 MB; all batches held: 0.8
