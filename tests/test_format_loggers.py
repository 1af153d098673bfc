"""Issue 13, deliverable 1: ``[format]`` describes real loggers' files, each
option on a file shaped like one (a vendor preamble, an IMU's gyroscope
columns, semicolons with decimal commas, millisecond stamps, ISO 8601 date-
times), and a bad description is one line naming the file (exit 2).

The truth is what the file was written from: each test writes known values
in a logger's layout and checks they come back exactly."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.formats.csv.reader import read_csv_capture
from rotcal.ingest.meta import CsvFormat, load_meta

sys.path.insert(0, str(Path(__file__).parent))
from posesim import hand_placed  # noqa: E402

# four samples: time (s) and three outputs with fractions, as a logger writes them
T_S = np.array([0.0, 0.01, 0.02, 0.03])
OUT = np.array([[15765.25, 288.5, -494.75], [15762.0, 284.25, -473.5], [15770.5, 290.0, -480.0],
                [15768.75, 286.5, -485.25]])


def rows(sep: str = ",", decimal: str = ".", t: list[str] | None = None) -> str:
    times = t if t is not None else [f"{x:.2f}" for x in T_S]
    return "".join(sep.join([ts, *(f"{x:.2f}".replace(".", decimal) if decimal != "." else f"{x:.2f}"
                                   for x in row)]) + "\n" for ts, row in zip(times, OUT))


def read(tmp_path: Path, text: str, toml: str = "") -> pl.DataFrame:
    """The capture read with the [format] of ``toml``, through dataset.toml's validation."""
    (tmp_path / "log.csv").write_text(text)
    (tmp_path / "dataset.toml").write_text(toml)
    meta = load_meta(tmp_path / "dataset.toml")
    return read_csv_capture(tmp_path / "log.csv", meta.csv_format, None, Limits())


def assert_samples(frame: pl.DataFrame, t_ns: np.ndarray | None = None) -> None:
    np.testing.assert_array_equal(frame["t_ns"].to_numpy(), np.round(T_S * 1e9) if t_ns is None else t_ns)
    np.testing.assert_array_equal(frame.select("u", "v", "w").to_numpy(), OUT)


def test_vendor_preamble_skipped(tmp_path):
    """A logger's `Fs,100` / `Waiting time,3` lines before its header."""
    text = "Fs,100\nWaiting time,3\nTime,AccX,AccY,AccZ\n" + rows()
    frame = read(tmp_path, text, '[format]\nskip_lines = 2\ncolumns = { t = "Time", u = "AccX", v = "AccY", w = "AccZ" }\n')
    assert_samples(frame)


def test_preamble_without_skip_lines_is_one_line_naming_it(tmp_path):
    text = "Fs,100\nWaiting time,3\nTime;AccX;AccY;AccZ\n" + rows(";")
    with pytest.raises(InputError, match="cannot detect the delimiter.*skip_lines") as err:
        read(tmp_path, text)
    assert "log.csv" in str(err.value) and "\n" not in str(err.value)


def test_semicolons_with_decimal_commas_detected(tmp_path):
    """A European spreadsheet export: `;` between fields, `,` in numbers."""
    text = "t;u;v;w\n" + rows(";", ",")
    assert "," in text
    assert_samples(read(tmp_path, text))


def test_tab_and_whitespace_detected(tmp_path):
    assert_samples(read(tmp_path, "t\tu\tv\tw\n" + rows("\t")))
    assert_samples(read(tmp_path, "   t     u     v     w\n" + rows("   ")))


def test_given_decimal_comma_with_whitespace(tmp_path):
    assert_samples(read(tmp_path, rows("  ", ","), '[format]\nheader = false\nnames = ["t", "u", "v", "w"]\ndecimal = ","\n'))


@pytest.mark.parametrize("prefix", ["%", "//"])
def test_comment_prefix(tmp_path, prefix):
    text = f"{prefix} MATLAB export\nt,u,v,w\n{prefix} started\n" + rows()
    assert_samples(read(tmp_path, text, f'[format]\ncomment_prefix = "{prefix}"\n'))


def test_names_rename_a_header(tmp_path):
    """`names` with a header used to be silently ignored."""
    text = "Zeit,Kanal 1,Kanal 2,Kanal 3,Status\n" + "".join(line.rstrip("\n") + ",ok\n" for line in rows().splitlines(True))
    assert_samples(read(tmp_path, text, '[format]\nnames = ["t", "u", "v", "w", ""]\n'))


@pytest.mark.parametrize("unit, scale", [("ms", 10**3), ("us", 10**6), ("ns", 10**9)])
def test_time_unit(tmp_path, unit, scale):
    """Millisecond (and finer) stamps, as integer counters write them; Unix-
    epoch stamps are exact to the nanosecond."""
    epoch_s = 1_709_647_331
    stamps = [f"{epoch_s * scale + round(x * scale)}" for x in T_S]
    frame = read(tmp_path, "t,u,v,w\n" + rows(t=stamps), f'[format]\ntime_unit = "{unit}"\n')
    assert_samples(frame, epoch_s * 10**9 + np.round(T_S * 1e9).astype(np.int64))


def test_time_unit_keeps_the_range_check(tmp_path):
    with pytest.raises(InputError, match=r"column 't', row 1 is 1e\+16, beyond ±9e\+09 s: time stamps in "
                                         r"ms, us or ns\? set dataset.toml \[format\] time_unit"):
        read(tmp_path, "t,u,v,w\n1e19,1,2,3\n", '[format]\ntime_unit = "ms"\n')


def test_iso8601_timestamps(tmp_path):
    stamps = ["2024-03-05T14:02:11.000Z", "2024-03-05T14:02:11.010Z", "2024-03-05T15:02:11.020+01:00",
              "2024-03-05T14:02:11.030"]
    frame = read(tmp_path, "t,u,v,w\n" + rows(t=stamps), '[format]\ntime_unit = "iso8601"\n')
    start_ns = 1_709_647_331 * 10**9  # 2024-03-05T14:02:11Z since the Unix epoch
    assert_samples(frame, start_ns + np.round(T_S * 1e9).astype(np.int64))


def test_iso8601_without_time_unit_says_how(tmp_path):
    with pytest.raises(InputError, match=r"'2024-03-05T14:02:11Z' is not a number; .*time_unit = \"iso8601\""):
        read(tmp_path, "t,u,v,w\n" + rows(t=["2024-03-05T14:02:11Z"] * 4))


def imu_file(path: Path, gyro_scale: float) -> None:
    """A six-pose session in an IMU logger's layout: accelerometer ax, ay,
    az, gyroscope gx, gy, gz (deg/s, times ``gyro_scale``), pose label."""
    labels = ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]
    d = np.repeat(np.eye(3), 2, axis=0) * np.tile([1.0, -1.0], 3)[:, None]
    sim = hand_placed(11, directions=d, samples=120)
    rng = np.random.default_rng(11)
    gyro = gyro_scale * rng.normal(0.0, 1.0, (len(sim.y), 3))
    pl.DataFrame({"t": sim.t_ns / 1e9, **{f"a{c}": sim.y[:, i] for i, c in enumerate("xyz")},
                  **{f"g{c}": gyro[:, i] for i, c in enumerate("xyz")},
                  "part": np.array(labels)[sim.pose]}).write_csv(path)


def test_imu_gyroscope_columns_are_not_taken_as_references(cli, tmp_path):
    """`ax, ay, az, gx, gy, gz` with u, v, w mapped to ax..az: the gyroscope
    used to be read as jig references (LinAlgError, exit 1)."""
    data = tmp_path / "imu"
    data.mkdir()
    imu_file(data / "imu.csv", 250.0)
    (data / "dataset.toml").write_text('[format]\ncolumns = { t = "t", u = "ax", v = "ay", w = "az" }\n'
                                       'pose_column = "part"\n')
    samples = load_dataset(data).samples
    assert samples["gx"].null_count() == samples.height
    status, _, err = cli("run", data, "--out", tmp_path / "o")
    assert status == 0, err
    poses = pl.read_parquet(tmp_path / "o" / "poses.parquet")
    assert poses["label"].to_list() == ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]


def test_gyroscope_read_as_reference_is_named(cli, tmp_path):
    """Without `columns`, a file's own gx, gy, gz are references in g; values
    that are no unit vectors are refused, saying what they look like."""
    data = tmp_path / "imu"
    data.mkdir()
    imu_file(data / "imu.csv", 250.0)
    text = (data / "imu.csv").read_text().replace("ax,ay,az", "u,v,w", 1)
    (data / "imu.csv").write_text(text)
    status, _, err = cli("run", data, "--out", tmp_path / "o")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1, err
    assert "imu.csv" in lines[0] and "reference column 'g" in lines[0] and "a gyroscope" in lines[0]
    peak = max(abs(pl.read_csv(data / "imu.csv")[c]).max() for c in ("gx", "gy", "gz"))
    assert f"values up to {peak:.4g}" in lines[0]


def test_references_in_m_s2_are_named(tmp_path):
    text = "t,u,v,w,gx,gy,gz\n0,1,2,3,0,0,9.81\n0.01,1,2,3,0,0,9.81\n"
    with pytest.raises(InputError, match=r"reference column 'gz' holds values up to 9.81.*in m/s\^2"):
        read(tmp_path, text)


def test_unit_references_within_a_few_percent_pass(tmp_path):
    text = "t,u,v,w,gx,gy,gz\n0,1,2,3,0.7071,0,0.7071\n0.01,1,2,3,0,0.99,0\n0.02,1,2,3,,,\n"
    assert read(tmp_path, text)["gx"].to_list() == [0.7071, 0.0, None]


@pytest.mark.parametrize("toml, text, needle", [
    ('[format]\ntime_unit = "min"\n', "t,u,v,w\n0,1,2,3\n", "format.time_unit = 'min' is not one of"),
    ('[format]\nskip_lines = 9\n', "Fs,100\nt,u,v,w\n0,1,2,3\n", "skip_lines = 9 skips the whole file (it has 3 lines)"),
    ('[format]\nnames = ["t", "u", "v"]\n', "t,u,v,w\n0,1,2,3\n",
     "names lists 3 names, the file's header has 4 columns (t, u, v, w)"),
    ("", "t|u|v|w\n0|1|2|3\n0.1|1|2|3\n", "cannot detect the delimiter"),
    ('[format]\ndelimiter = ","\ndecimal = ","\n', "t,u,v,w\n0,1,2,3\n", "decimal = \",\" needs a delimiter other"),
    ('[format]\ntime_unit = "iso8601"\n', "t,u,v,w\n2024-03-05T14:02:11Z,1,2,3\nlater,1,2,3\n",
     "column 't', row 2: 'later' is not an ISO 8601 date-time"),
], ids=["unknown unit", "skip_lines beyond the file", "names of the wrong length", "undetectable delimiter",
        "decimal comma between commas", "bad ISO date-time"])
def test_bad_description_is_one_line_naming_the_file(cli, tmp_path, toml, text, needle):
    data = tmp_path / "dut"
    data.mkdir()
    (data / "log.csv").write_text(text)
    (data / "dataset.toml").write_text(toml)
    status, _, err = cli("run", data, "--out", tmp_path / "o")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and "Traceback" not in err, err
    assert needle in lines[0], lines[0]
    assert ("dataset.toml" if "format." in needle else "log.csv") in lines[0]


def test_default_format_detects_the_comma_files_it_always_read(tmp_path):
    """The detected delimiter of a plain file is the old default's comma."""
    assert_samples(read(tmp_path, "t, u, v, w\n" + rows(", ")))
    assert CsvFormat().delimiter is None and CsvFormat().decimal_comma is None


def test_fractional_milliseconds_with_decimal_commas(tmp_path):
    stamps = ["0,5", "10,5", "20,5", "30,5"]
    frame = read(tmp_path, "t;u;v;w\n" + rows(";", ",", t=stamps), '[format]\ntime_unit = "ms"\n')
    assert_samples(frame, np.round(T_S * 1e9) + 500_000)
