"""Issue 17, hostile CSV captures and paths: capture files are opened
literally (never as glob patterns), inside their dataset, only when they are
regular files; every value that enters is finite and within range, and no fit
is "ok" with a non-finite coefficient."""

import os
import shutil
import signal
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from rotcal.config import FitConfig, Limits
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.formats.csv.reader import read_csv_capture
from rotcal.ingest.meta import CsvFormat
from rotcal.simulate import Plan, SimulationSpec

SMALL = SimulationSpec(plan=Plan(rates_hz=(0.1,), rotation_samples=600, step_samples=10))
GOOD = "t,u,v,w\n0.00,10,20,30\n0.01,11,21,31\n"


@pytest.fixture
def dataset(make_dataset, tmp_path):
    """A fresh copy of a small CSV dataset the test may damage."""
    dst = tmp_path / "dut"
    shutil.copytree(make_dataset(1, spec=SMALL), dst)
    return dst


def rotation_csv(directory: Path) -> Path:
    return sorted(directory.glob("*_0.1hz.csv"))[0]


def set_value(csv: Path, column: str, row: int, text: str) -> None:
    """Write ``text`` as ``column`` of data row ``row`` (1-based) of ``csv``."""
    lines = csv.read_bytes().split(b"\n")
    cells = lines[row].split(b",")
    cells[lines[0].split(b",").index(column.encode())] = text.encode()
    lines[row] = b",".join(cells)
    csv.write_bytes(b"\n".join(lines))


def one_line_error(result, *needles):
    status, out, err = result
    lines = [line for line in err.splitlines() if line.strip()]
    assert status == 2 and len(lines) == 1 and "Traceback" not in err, (status, err)
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def test_capture_named_like_a_glob_pattern_is_read_literally(tmp_path):
    """'x[yz].csv' is that file, not the pattern matching 'xz.csv' beside it."""
    (tmp_path / "xz.csv").write_text("t,u,v,w\n0.00,99,99,99\n")
    literal = tmp_path / "x[yz].csv"
    literal.write_text(GOOD)
    frame = read_csv_capture(literal, CsvFormat(), None, Limits())
    assert frame["u"].to_list() == [10.0, 11.0]


def test_dataset_named_like_a_glob_pattern_has_its_own_data(tmp_path):
    for name, u in (("lot1", 99), ("lot[1]", 10)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "a.csv").write_text(f"t,u,v,w\n0.00,{u},20,30\n")
    assert load_dataset(tmp_path / "lot[1]").samples["u"].to_list() == [10.0]


def test_auto_found_symlink_out_of_the_dataset_is_refused(cli, dataset, tmp_path):
    """rotcal run follows no link found in the directory out of the dataset."""
    outside = tmp_path / "outside.csv"
    shutil.copy(rotation_csv(dataset), outside)
    (dataset / "zz_link.csv").symlink_to(outside)
    one_line_error(cli("run", dataset, "--out", tmp_path / "o"), "zz_link.csv", "pointing outside the dataset directory")


def test_symlink_inside_the_dataset_is_followed(dataset, tmp_path):
    csv = rotation_csv(dataset)
    before = load_dataset(dataset).samples.height
    (dataset / "sub").mkdir()
    csv.rename(dataset / "sub" / csv.name)
    csv.symlink_to(Path("sub") / csv.name)
    assert load_dataset(dataset).samples.height == before


@pytest.fixture
def alarm():
    """A test that would hang fails after 20 s instead."""
    def expire(*_):
        raise TimeoutError("hung")
    previous = signal.signal(signal.SIGALRM, expire)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, previous)


def test_fifo_capture_is_refused_not_waited_on(cli, dataset, tmp_path, alarm):
    os.mkfifo(dataset / "trap.csv")
    one_line_error(cli("run", dataset, "--out", tmp_path / "o"), "trap.csv", "not a regular file")


def test_fifo_given_as_the_dataset_is_refused(cli, tmp_path, alarm):
    os.mkfifo(tmp_path / "trap.csv")
    one_line_error(cli("run", tmp_path / "trap.csv", "--out", tmp_path / "o"), "trap.csv", "not a regular file (a FIFO)")


def test_fifo_read_directly_is_refused(tmp_path, alarm):
    os.mkfifo(tmp_path / "trap.csv")
    with pytest.raises(InputError, match="not a regular file"):
        read_csv_capture(tmp_path / "trap.csv", CsvFormat(), None, Limits())


@pytest.mark.parametrize("column, text, needle", [
    ("angle_deg", "1e308", "column 'angle_deg', row 5 is 1e+308"),
    ("u", "1e308", "column 'u', row 5 is 1e+308"),
    ("w", "-inf", "column 'w', row 5 is -inf"),
    ("rate_hz", "nan", "column 'rate_hz', row 5 is NaN"),
    ("angle_deg", "inf", "column 'angle_deg', row 5 is inf"),
    ("t", "1e12", "column 't', row 5 is 1e+12"),
    ("t", "-1e15", "column 't', row 5 is -1e+15"),
])
def test_non_finite_or_absurd_value_is_an_input_error(cli, dataset, tmp_path, column, text, needle):
    """Each was a traceback (int64 overflow, a singular matrix downstream) or
    nine NaN parameters with fit status "ok"."""
    csv = rotation_csv(dataset)
    set_value(csv, column, 5, text)
    one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, needle)


@pytest.mark.parametrize("column", ["gx", "gy", "gz", "temperature_c"])
def test_optional_columns_are_checked_too(tmp_path, column):
    path = tmp_path / "log.csv"
    path.write_text(f"t,u,v,w,{column}\n0.00,10,20,30,1\n0.01,11,21,31,inf\n")
    with pytest.raises(InputError, match=f"column '{column}', row 2 is inf"):
        read_csv_capture(path, CsvFormat(), None, Limits())


def test_empty_optional_cell_is_still_allowed(tmp_path):
    path = tmp_path / "log.csv"
    path.write_text("t,u,v,w,temperature_c\n0.00,10,20,30,\n0.01,11,21,31,25\n")
    assert read_csv_capture(path, CsvFormat(), None, Limits())["temperature_c"].to_list() == [None, 25.0]


@pytest.mark.parametrize("damage, needles", [
    (lambda data: data.replace(b",x,", b",x\xff,", 1), ("not valid UTF-8",)),
    (lambda data: data + b'1,2,"3\n', ("unterminated quote",)),
], ids=["non-UTF-8 byte", "unterminated quote"])
def test_unreadable_text_is_one_line(cli, dataset, tmp_path, damage, needles):
    csv = rotation_csv(dataset)
    csv.write_bytes(damage(csv.read_bytes()))
    one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, *needles)


def test_whitespace_file_reads_as_before(tmp_path):
    """Runs of blanks and tabs separate; blanks that open or close a line
    do not make empty columns."""
    path = tmp_path / "log.txt"
    path.write_bytes(b"  0.00 \t10  20 30\t\n0.01 11 21 31   \n\t0.02 12 22 32")
    fmt = CsvFormat(delimiter="whitespace", header=False, names=("t", "u", "v", "w"))
    frame = read_csv_capture(path, fmt, None, Limits())
    assert frame.select("t_ns", "u", "v", "w").rows() == [
        (0, 10.0, 20.0, 30.0), (10_000_000, 11.0, 21.0, 31.0), (20_000_000, 12.0, 22.0, 32.0)]


def test_whitespace_file_read_in_blocks_matches_one_read(tmp_path, monkeypatch):
    """Block boundaries (here every few hundred bytes) change nothing."""
    from rotcal.ingest.formats.csv import reader as csv_source

    rng = np.random.default_rng(0)
    rows = [f"{' ' * int(rng.integers(0, 3))}{i * 0.01:.2f}{' ' * int(rng.integers(1, 4))}{i}\t{-i} {2 * i}"
            f"{' ' * int(rng.integers(0, 3))}" for i in range(400)]
    path = tmp_path / "log.txt"
    path.write_text("\n".join(rows) + "\n")
    fmt = CsvFormat(delimiter="whitespace", header=False, names=("t", "u", "v", "w"))
    whole = read_csv_capture(path, fmt, None, Limits())
    monkeypatch.setattr(csv_source, "_SCAN_BLOCK", 333)
    assert read_csv_capture(path, fmt, None, Limits()).equals(whole)
    assert whole["v"].to_list() == [-float(i) for i in range(400)]


def test_fit_with_a_non_finite_coefficient_is_a_failure_row():
    """Second line of defence: an angle that overflows the sine fit cannot
    give an "ok" fit of NaN coefficients."""
    from rotcal.fit.segments import fit_segment

    theta = np.linspace(0.0, 720.0, 200)
    theta[50] = 1e308
    c, s = np.cos(np.radians(theta)), np.sin(np.radians(theta))
    with np.errstate(all="ignore"):
        fit = fit_segment(0, "rotation", 0.1, "column", theta, np.column_stack([c, s, 2.0 + c - s]), FitConfig())
    assert fit.status == "failed" and "not finite" in fit.reason


def test_good_dataset_still_runs(cli, dataset, tmp_path):
    status, out, err = cli("run", dataset, "--out", tmp_path / "o")
    assert status == 0, err
    fits = pl.read_parquet(tmp_path / "o" / "fits.parquet")
    assert (fits["status"] == "ok").all()


def test_whitespace_file_is_converted_without_copies_of_the_whole_text(tmp_path, monkeypatch):
    """A whitespace-delimited file of one-digit values took some 40 times its
    size (regular expressions over the whole text: a bytes object per token);
    block by block it takes about twice, the result and its parts, besides
    the block's own arrays (blocks of 64 KiB here, for a small file)."""
    import tracemalloc

    from rotcal.ingest.formats.csv import reader as csv_source

    monkeypatch.setattr(csv_source, "_SCAN_BLOCK", 1 << 16)
    path = tmp_path / "log.txt"
    digits = np.random.default_rng(0).integers(0, 10, (100_000, 3))
    path.write_text("".join(f" {i} {a} {b}  {c} \n" for i, (a, b, c) in enumerate(digits)))
    fmt = CsvFormat(delimiter="whitespace", header=False, names=("t", "u", "v", "w"))
    tracemalloc.start()
    try:
        frame = read_csv_capture(path, fmt, None, Limits())
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert frame["u"].to_list() == digits[:, 0].astype(float).tolist()
    size = path.stat().st_size
    assert peak < 4 * size, f"{peak / size:.1f} times the file"


@pytest.mark.parametrize("trailing_newline", [True, False])
@pytest.mark.parametrize("row", [0, 1, 4, 7])
@pytest.mark.parametrize(("excess", "refused"), [(0, False), (1, True)])
def test_a_line_one_byte_over_the_limit_is_refused_wherever_it_falls(tmp_path, row, excess, refused, trailing_newline):
    """A line of exactly ``max_line_bytes`` is read, one byte more refused,
    whichever of the guard's half-limit spans it straddles (rows of varying
    offset, the last line with or without its newline)."""
    limit = 64
    rows = [f"0.0{k},1,2,3" for k in range(8)]
    rows[row] = f"0.0{row},1." + "0" * (limit + excess - 11) + ",2,3"  # 11 bytes around the zeros
    assert len(rows[row]) == limit + excess
    path = tmp_path / "long.csv"
    path.write_text("t,u,v,w\n" + "\n".join(rows) + ("\n" if trailing_newline else ""))
    if refused:
        with pytest.raises(InputError, match=f"a line is longer than the limit of {limit} bytes"):
            read_csv_capture(path, CsvFormat(), None, Limits(max_line_bytes=limit))
    else:
        frame = read_csv_capture(path, CsvFormat(), None, Limits(max_line_bytes=limit))
        assert frame.height == 8 and frame["u"].to_list() == [1.0] * 8


def test_comment_lines_anywhere_and_labels_written_otherwise(tmp_path):
    """A comment deep in the data is skipped, labels in capitals or with
    blanks are read as x, y, z (the labels are parsed as the sample table's
    type only where all are written so)."""
    path = tmp_path / "labels.csv"
    path.write_text("t,u,v,w,axis\n0.00,10,20,30,X\n0.01,11,21,31, y\n# paused\n0.02,12,22,32,z\n")
    frame = read_csv_capture(path, CsvFormat(), None, Limits())
    assert frame["axis"].cast(pl.String).to_list() == ["x", "y", "z"]
    assert frame["t_ns"].to_list() == [0, 10_000_000, 20_000_000] and frame["w"].to_list() == [30.0, 31.0, 32.0]
