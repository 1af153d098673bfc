"""Every bad input of issue 2: a one-line message naming the file and the
problem, a non-zero exit, and no traceback."""

import shutil
from pathlib import Path

import polars as pl
import pytest

from rotcal.simulate import Plan, SimulationSpec

SMALL = SimulationSpec(plan=Plan(rates_hz=(0.1,), rotation_samples=600, step_samples=10))


@pytest.fixture
def dataset(make_dataset, tmp_path):
    """A fresh copy of a small CSV dataset the test may damage."""
    src = make_dataset(1, spec=SMALL)
    dst = tmp_path / "dut"
    shutil.copytree(src, dst)
    return dst


@pytest.fixture
def mcap_dataset(make_dataset, tmp_path):
    src = make_dataset(1, fmt="mcap-cdr", spec=SMALL)
    dst = tmp_path / "dut"
    shutil.copytree(src, dst)
    return dst


def first_csv(directory: Path) -> Path:
    return sorted(directory.glob("*.csv"))[0]


def assert_one_line_error(result, *needles, code=2):
    status, out, err = result
    assert status == code, (status, out, err)
    lines = [line for line in err.strip().splitlines() if line]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for needle in needles:
        assert needle in lines[0], lines[0]


def rewrite(path: Path, transform) -> None:
    lines = path.read_text().splitlines()
    path.write_text("\n".join(transform(lines)) + "\n")


def test_missing_required_column(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    pl.read_csv(csv).drop("v").write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "missing required column 'v'")


def test_message_keeps_the_dataset_toml_table_it_names(cli, dataset, tmp_path):
    """A message quoting [format] (or a path with brackets) is printed as it
    is, not read as console markup and dropped."""
    csv = first_csv(dataset)
    pl.read_csv(csv).drop("v").write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), "(map the file's columns in dataset.toml [format] columns)")


def test_non_numeric_value(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    rewrite(csv, lambda lines: lines[:5] + [lines[5].replace(lines[5].split(",")[1], "12x4", 1)] + lines[6:])
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "column 'u', row 5", "'12x4' is not a number")


def test_nan_value(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    frame = pl.read_csv(csv)
    frame.with_columns(w=pl.when(pl.int_range(pl.len()) == 7).then(float("nan")).otherwise(pl.col("w"))).write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "column 'w', row 8 is NaN")


def test_empty_cell(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    pl.read_csv(csv).with_columns(u=pl.when(pl.int_range(pl.len()) == 2).then(None).otherwise(pl.col("u"))).write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "column 'u', row 3 is empty")


def test_time_going_backwards(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    frame = pl.read_csv(csv)
    t = frame["t"].to_list()
    t[3], t[4] = t[4], t[3]
    frame.with_columns(t=pl.Series(t)).write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "time goes backwards at row 5")


def test_empty_file(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    csv.write_text("")
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "empty")


def test_header_only_file(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    rewrite(csv, lambda lines: lines[:1])
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "no samples")


def test_unknown_axis_label(cli, dataset, tmp_path):
    csv = first_csv(dataset)
    pl.read_csv(csv).with_columns(axis=pl.lit("q")).write_csv(csv)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), csv.name, "unknown axis label 'q'")


def test_truncated_mcap(cli, mcap_dataset, tmp_path):
    mcap = mcap_dataset / "capture.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) // 2])
    assert_one_line_error(cli("run", mcap_dataset, "--out", tmp_path / "o"), "capture.mcap", "truncated MCAP")


def test_corrupt_mcap(cli, mcap_dataset, tmp_path):
    mcap = mcap_dataset / "capture.mcap"
    data = bytearray(mcap.read_bytes())
    data[40:4000] = bytes(3960)
    mcap.write_bytes(bytes(data))
    assert_one_line_error(cli("run", mcap_dataset, "--out", tmp_path / "o"), "capture.mcap", "MCAP")


def test_not_an_mcap(cli, mcap_dataset, tmp_path):
    (mcap_dataset / "capture.mcap").write_text("t,u,v,w\n0,1,2,3\n")
    assert_one_line_error(cli("run", mcap_dataset, "--out", tmp_path / "o"), "capture.mcap", "MCAP")


def test_topic_that_is_not_there(cli, mcap_dataset, tmp_path):
    with (mcap_dataset / "dataset.toml").open("a") as fh:
        fh.write('\n[mcap]\nimu_topic = "/accel"\n')
    assert_one_line_error(cli("run", mcap_dataset, "--out", tmp_path / "o"), "capture.mcap", "topic '/accel' is not in the file", "/imu")


@pytest.mark.parametrize(
    "toml, needles",
    [
        ('[site]\ng_local = "high"\n', ["dataset.toml", "site.g_local", "not of type 'number'"]),
        ('[site]\ng_local = 98.1\n', ["dataset.toml", "site.g_local", "98.1"]),
        ('[format]\ndelimiter = "|"\n', ["dataset.toml", "format.delimiter"]),
        ('[sitee]\ng_local = 9.8\n', ["dataset.toml", "unknown table or key 'sitee'"]),
        ('[site\ng_local = 9.8\n', ["dataset.toml", "not valid TOML"]),
        ('[[capture]]\nfile = "x.csv"\naxis = "q"\n', ["dataset.toml", "capture.0.axis"]),
        # read twice, every record was a duplicate: the run ended "no rate can be determined" (exit 3)
        ('[[capture]]\nfile = "x.csv"\n[[capture]]\nfile = "x.csv"\naxis = "x"\n',
         ["dataset.toml", "[[capture]] file 'x.csv' is named twice"]),
    ],
)
def test_malformed_dataset_toml(cli, dataset, tmp_path, toml, needles):
    (dataset / "dataset.toml").write_text(toml)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), *needles)


def test_missing_meta_file(cli, dataset, tmp_path):
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o", "--meta", tmp_path / "nope.toml"), "nope.toml", "not found")


def test_missing_gravity_uses_standard_gravity_and_says_so(cli, dataset, tmp_path):
    (dataset / "dataset.toml").write_text('[device]\noutput_unit = "bit"\n')
    status, out, err = cli("run", dataset, "--out", tmp_path / "o")
    assert status == 0
    assert "g_local not given: using standard gravity 9.80665 m/s^2" in err


def test_capture_outside_dataset_is_refused(cli, dataset, tmp_path):
    (dataset / "dataset.toml").write_text('[[capture]]\nfile = "../elsewhere.csv"\n')
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), "points outside the dataset directory")


def test_short_segment_is_a_failure_row_not_fatal(cli, dataset, tmp_path):
    rot = sorted(dataset.glob("*_0.1hz.csv"))[0]
    rewrite(rot, lambda lines: lines[:6])  # 5 samples
    status, out, err = cli("run", dataset, "--out", tmp_path / "o")
    assert status == 0, err
    assert "warning:" in err and "too short: 5 samples" in err
    fits = pl.read_parquet(tmp_path / "o" / "fits.parquet")
    failed = fits.filter(pl.col("status") == "failed")
    assert failed.height == 3 and failed["reason"][0].startswith("too short")
    # two remaining axes still determine 0.1 Hz: every component is measured at least once
    intrinsic = pl.read_parquet(tmp_path / "o" / "intrinsic.parquet")
    assert sorted(set(intrinsic["rate_hz"])) == [0.0, 0.1]


def test_run_fails_only_when_nothing_can_be_determined(cli, dataset, tmp_path):
    for csv in sorted(dataset.glob("*.csv")):
        if not csv.name.startswith("00_"):
            csv.unlink()
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), "no rate can be determined", code=3)
    assert (tmp_path / "o" / "fits.parquet").exists()


def test_missing_dataset(cli, tmp_path):
    assert_one_line_error(cli("run", tmp_path / "absent", "--out", tmp_path / "o"), "absent", "dataset not found")


def test_headerless_file_wider_than_its_names(tmp_path):
    """[format] names may list the first columns only: the logger's further
    columns are left out, as a header file's unknown columns are."""
    from rotcal.config import Limits
    from rotcal.ingest.formats.csv.reader import read_csv_capture
    from rotcal.ingest.meta import CsvFormat

    path = tmp_path / "log.txt"
    path.write_text("0.00  10 20 30  7 8\n0.01  11 21 31  7 8\n")
    fmt = CsvFormat(delimiter="whitespace", header=False, names=("t", "u", "v", "w"))
    frame = read_csv_capture(path, fmt, None, Limits())
    assert frame.select("t_ns", "u", "v", "w").rows() == [(0, 10.0, 20.0, 30.0), (10_000_000, 11.0, 21.0, 31.0)]


@pytest.mark.parametrize("text, needles", [
    ("0.00 10 20\n0.01 11 21\n", ("fewer columns than the 4 that dataset.toml [format] names lists",)),
    ("t u v w\n0.00 10 20 30\n", ("column 't', row 1: 't' is not a number",)),
], ids=["narrower than its names", "a header row read as data"])
def test_headerless_file_that_does_not_match_its_names(cli, tmp_path, text, needles):
    data = tmp_path / "dut"
    data.mkdir()
    (data / "log.txt").write_text(text)
    (data / "dataset.toml").write_text('[format]\ndelimiter = "whitespace"\nheader = false\nnames = ["t", "u", "v", "w"]\n\n'
                                       '[[capture]]\nfile = "log.txt"\n')
    assert_one_line_error(cli("run", data, "--out", tmp_path / "o"), "log.txt", *needles)


def test_pose_column_that_is_also_a_contract_column(cli, dataset, tmp_path):
    (dataset / "dataset.toml").write_text((dataset / "dataset.toml").read_text() + '\n[format]\npose_column = "axis"\n')
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), first_csv(dataset).name,
                          "dataset.toml [format] pose_column 'axis' is the file's 'axis' column too")


@pytest.mark.parametrize("text, fmt", [
    ("t,u,v,w\n0.00,10,20,30\n\n0.01,11,21,31\n\n\n", {}),
    ("t,u,v,w\r\n0.00,10,20,30\r\n0.01,11,21,31\r\n\r\n", {}),
    ("0.00 10 20 30\n0.01 11 21 31\n\n", {"delimiter": "whitespace", "header": False, "names": ("t", "u", "v", "w")}),
], ids=["comma", "crlf", "headerless whitespace"])
def test_blank_lines_are_not_samples(tmp_path, text, fmt):
    """A logger's trailing (or stray) blank lines are no rows: they used to
    stop the run as 'column 'u', row 3 is empty'."""
    from rotcal.config import Limits
    from rotcal.ingest.formats.csv.reader import read_csv_capture
    from rotcal.ingest.meta import CsvFormat

    path = tmp_path / "log.csv"
    path.write_bytes(text.encode())
    frame = read_csv_capture(path, CsvFormat(**fmt), None, Limits())
    assert frame.select("t_ns", "u", "v", "w").rows() == [(0, 10.0, 20.0, 30.0), (10_000_000, 11.0, 21.0, 31.0)]


@pytest.mark.parametrize("toml, needle", [
    ('[plan]\nstep_deg = 0.0\n', "plan: step_deg = 0.0 must be a number > 0"),
    ('[plan]\ndt_s = -0.06\n', "plan: dt_s = -0.06 must be a number > 0"),
    ('[plan]\nrotation_samples = 0\n', "plan: rotation_samples = 0 must be a whole number of at least 1"),
    ('[plan]\naxes = ["q"]\n', "plan: axes = ['q'] must be a non-empty list of x, y, z"),
    ('[plan]\nrates_hz = "0.5"\n', "plan: rates_hz = '0.5' must be a list of numbers"),
    ('[plan]\ncontinuous = true\nramp_deg_s2 = 0.0\n', "plan: ramp_deg_s2 = 0.0 must be a number > 0"),
    ('[dut]\nsensitivity_spread = -4.0\n', "dut: sensitivity_spread = -4.0 must be a number >= 0"),
    ('[[effect]]\nname = "centripetal"\naxis = "x"\nradius_m = "big"\n', "[[effect]] centripetal: radius_m = 'big' is not a number"),
    ('[timebase]\ngap_count = 3\ngap_s = 100000.0\n', "timebase: 3 gaps of 100000 s leave no sample of the recording"),
])
def test_simulation_file_with_a_value_no_plan_can_have(cli, tmp_path, toml, needle):
    """Each stopped rotcal simulate with a traceback (division by zero, an
    empty array, a string multiplied by a float)."""
    path = tmp_path / "sim.toml"
    path.write_text(toml)
    assert_one_line_error(cli("simulate", tmp_path / "d", "--config", path), needle)


def test_header_with_spaces_after_the_commas(tmp_path):
    """'t, u, v, w' names the contract columns: the file was refused as
    missing 'u', 'v', 'w' while listing u, v, w among the columns found."""
    from rotcal.config import Limits
    from rotcal.ingest.formats.csv.reader import read_csv_capture
    from rotcal.ingest.meta import CsvFormat

    path = tmp_path / "log.csv"
    path.write_text("t, u, v, w, axis, rate_hz, angle_deg\n0.00, 10, 20, 30, x, 0, 15\n0.01, 11, 21, 31, x, 0, 15\n")
    frame = read_csv_capture(path, CsvFormat(), None, Limits())
    assert frame.select("t_ns", "u", "v", "w", "rate_hz", "angle_deg").rows() == [
        (0, 10.0, 20.0, 30.0, 0.0, 15.0), (10_000_000, 11.0, 21.0, 31.0, 0.0, 15.0)]
    assert frame["axis"].to_list() == ["x", "x"]
