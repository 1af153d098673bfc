"""Issue 17's hostile dataset.toml, configuration, output directory and batch
inputs: each is a one-line error (exit 2) naming the file and the problem,
or, in a batch, that dataset's quarantine row, while every other dataset is
published; names are escaped wherever they are printed."""

import os
import shutil
import sqlite3

import polars as pl
import pytest
from test_bad_input import assert_one_line_error

from rotcal.batch.manifest import Manifest
from rotcal.batch.runner import run_batch

from batch_support import REPO, SERIAL, SMALL, config_file, make_root, manifest_rows

DEEP = "x = " + "{a = " * 400 + "1" + "}" * 400 + "\n"  # 2.4 KB: RecursionError in tomllib


@pytest.fixture
def dataset(make_dataset, tmp_path):
    dst = tmp_path / "dut"
    shutil.copytree(make_dataset(1, spec=SMALL), dst)
    return dst


@pytest.mark.parametrize(
    "toml, needles",
    [
        (DEEP, ["dataset.toml", "nested more than"]),
        ("[device]\nfull_scale = " + "9" * 5000 + "\n", ["dataset.toml", "line 2", "64-bit"]),
        ("[device]\nfull_scale = " + "9" * 400 + "\n", ["dataset.toml", "device.full_scale", "64-bit"]),
        ("[device]\nfull_scale = 9223372036854775808\n", ["dataset.toml", "device.full_scale", "64-bit"]),
        ('[[capture]]\nfile = "00_x_static.csv\\u0000"\n', ["dataset.toml", "capture.0.file", "NUL"]),
        ("[site]\ng_local = nan\n", ["dataset.toml", "site.g_local", "not a finite number"]),
        ("[site]\ng_local = 9.8\ng_local_uncertainty = nan\n", ["dataset.toml", "site.g_local_uncertainty", "finite"]),
        ("[device]\nfull_scale = inf\n", ["dataset.toml", "device.full_scale", "finite"]),
        ("[plan]\nrates_hz = [0.5, -inf]\n", ["dataset.toml", "plan.rates_hz.1", "finite"]),
        ("[[capture]]\nfile = \"00_x_static.csv\"\nrate_hz = 1e400\n", ["dataset.toml", "capture.0.rate_hz", "finite"]),
    ],
    ids=["deep", "5000_digits", "400_digits", "2^63", "nul", "g_nan", "u_nan", "inf", "rate_list_inf", "1e400"],
)
def test_hostile_dataset_toml_is_a_one_line_error(cli, dataset, tmp_path, toml, needles):
    (dataset / "dataset.toml").write_text(toml)
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o"), *needles)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_config_refuses_non_finite_numbers(cli, dataset, tmp_path, value):
    config = tmp_path / "c.toml"
    config.write_text(f"[diagnosis]\nfalse_alarm = {value}\n")
    assert_one_line_error(cli("run", dataset, "--out", tmp_path / "o", "--config", config),
                          "c.toml", "diagnosis.false_alarm", "finite")


def test_one_broken_dataset_toml_of_each_kind_stops_nothing(tmp_path, monkeypatch):
    """Each hostile dataset.toml, and an exception no one expected while a
    dataset is planned, becomes that dataset's quarantine row with its
    one-line reason; the good datasets are published."""
    root, out = tmp_path / "root", tmp_path / "out"
    good = make_root(root, [1, 2])
    hostile = {"deep": DEEP, "digits": "[device]\nfull_scale = " + "9" * 5000 + "\n",
               "nul": '[[capture]]\nfile = "a\\u0000.csv"\n', "nan": "[site]\ng_local = nan\n"}
    for name, text in hostile.items():
        shutil.copytree(root / good[0], root / name)
        (root / name / "dataset.toml").write_text(text)
    shutil.copytree(root / good[0], root / "bug")
    from rotcal.batch import plan

    real = plan.dataset_inputs

    def buggy(source, limits):
        if source.name == "bug":
            raise KeyError("a bug")
        return real(source, limits)

    monkeypatch.setattr(plan, "dataset_inputs", buggy)
    summary = run_batch(root, out, SERIAL)
    assert (summary.ok, summary.quarantined, summary.errors, summary.exit_status) == (2, 5, 0, 4)
    reasons = {p["dataset_path"]: p["reason"] for p in summary.problems}
    assert set(reasons) == set(hostile) | {"bug"}
    for reason in reasons.values():
        assert "\n" not in reason and "Traceback" not in reason, reason
    assert reasons["bug"] == f"{root / 'bug'}: unexpected KeyError while planning (a bug: please report it): 'a bug'"
    assert "nested more than" in reasons["deep"] and "not a finite number" in reasons["nan"]
    assert run_batch(root, out, SERIAL).processed == 0  # the quarantines hold until the dataset changes


def test_a_folder_that_cannot_be_listed_is_quarantined_and_the_rest_published(tmp_path, monkeypatch):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    (root / "closed" / "deeper").mkdir(parents=True)
    real = os.scandir

    def scandir(path):  # what a directory without read permission gives a user other than root
        if os.fspath(path) == str(root / "closed"):
            raise PermissionError(13, "Permission denied", os.fspath(path))
        return real(path)

    monkeypatch.setattr("rotcal.batch.plan.os.scandir", scandir)
    summary = run_batch(root, out, SERIAL)
    assert (summary.ok, summary.quarantined, summary.exit_status) == (1, 1, 4)
    problem = summary.problems[0]
    assert problem["dataset_path"] == "closed" and "closed" in problem["reason"] and "cannot be read" in problem["reason"]


# -- output directories -----------------------------------------------------------------

def _not_computed(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("computed before the output directory was checked")

    monkeypatch.setattr("rotcal.run._run", fail)
    monkeypatch.setattr("rotcal.batch.runner._run", fail)


@pytest.mark.parametrize("command", ["run", "batch"])
def test_an_output_directory_that_cannot_be_written_is_refused_before_any_work(cli, dataset, tmp_path, monkeypatch,
                                                                              command):
    _not_computed(monkeypatch)
    source = dataset if command == "run" else dataset.parent
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert_one_line_error(cli(command, source, "--out", a_file), "a_file", "is not a directory")
    assert_one_line_error(cli(command, source, "--out", a_file / "sub"), "a_file", "is not a directory")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    if os.access(locked, os.W_OK):  # root writes anywhere: what the kernel would answer for another user
        real = os.access
        monkeypatch.setattr(os, "access", lambda path, mode: real(path, mode) and not (path == locked and mode & os.W_OK))
    try:
        assert_one_line_error(cli(command, source, "--out", locked), "locked", "cannot be written")
        assert_one_line_error(cli(command, source, "--out", locked / "new"), "locked", "cannot be written")
    finally:
        locked.chmod(0o755)


# -- names, consoles and the manifest ---------------------------------------------------------

def test_control_characters_in_names_are_escaped_and_markup_and_emoji_are_not_read(cli, tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    names = ["forged\n2026-01-01T00:00:00.000Z rotcal batch: all ok", "\x1b[31mred", ":x: [bold]b", "[link=x]y"]
    for name in names:
        (root / name).mkdir()
        (root / name / "dataset.toml").write_text("[site]\ng_local = nan\n")  # quarantined: its name in the log line
    status, stdout, err = cli("batch", root, "--out", out, "--workers", "1", "--config", config_file(tmp_path))
    assert status == 4, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 + 1 + len(names), err  # the count, one line per dataset
    assert "\x1b" not in err + stdout and "\u274c" not in err + stdout
    assert sum("forged\\n2026" in line for line in lines) == 1 and sum("\\x1b[31mred" in line for line in lines) == 1
    assert sum(":x: [bold]b" in line for line in lines) == 1 and sum("[link=x]y" in line for line in lines) == 1
    assert sum("\\x1b" in line for line in stdout.splitlines()) == 1  # the summary escapes the names too
    rows = manifest_rows(out)
    assert names[1] in rows  # the manifest keeps the true name; only what is printed is escaped


def test_run_messages_are_not_read_as_emoji_or_markup(cli, dataset, tmp_path):
    (dataset / "dataset.toml").write_text('[device]\noutput_unit = ":x: [/]"\n[site]\ng_local = 9.81\n')
    status, stdout, err = cli("run", dataset, "--out", tmp_path / "o")
    assert status == 0, err
    assert "\u274c" not in stdout + err and ":x: [/]" in stdout


def test_a_killed_run_is_marked_interrupted_by_the_next(tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    out.mkdir()
    manifest = Manifest(out / "manifest.sqlite")
    manifest.start_run("killed-1", "2026-01-01T00:00:00.000Z", str(root), "local", 1, "0")
    manifest.close()
    summary = run_batch(root, out, SERIAL)
    with sqlite3.connect(out / "manifest.sqlite") as db:
        rows = dict(db.execute("SELECT run_id, status FROM batch_runs"))
    assert rows == {"killed-1": "interrupted", summary.run_id: "finished"}
    assert "1 earlier run was interrupted (killed-1)" in summary.notes


def test_a_manifest_without_the_status_column_gains_it(tmp_path):
    path = tmp_path / "manifest.sqlite"
    with sqlite3.connect(path) as db:  # as rotcal before the column wrote it
        db.execute("CREATE TABLE batch_runs (run_id TEXT, started_at TEXT, finished_at TEXT, root TEXT, executor TEXT, "
                   "workers INTEGER, rotcal_version TEXT, summary TEXT, PRIMARY KEY (run_id))")
        db.execute("INSERT INTO batch_runs (run_id, started_at) VALUES ('old', 'x')")
    Manifest(path).close()
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT run_id, status FROM batch_runs").fetchall() == [("old", None)]


# -- a copied capture -----------------------------------------------------------------------

def test_a_copied_capture_is_read_once_with_one_note(cli, dataset, tmp_path):
    status, _, err = cli("run", dataset, "--out", tmp_path / "one", "--quiet")
    assert status == 0, err
    original = sorted(dataset.glob("*.csv"))[1]
    shutil.copyfile(original, dataset / "zz_copy.csv")
    status, _, err = cli("run", dataset, "--out", tmp_path / "two", "--quiet")
    assert status == 0, err
    duplicate = [line for line in err.splitlines() if "duplicate capture" in line]
    assert len(duplicate) == 1 and "zz_copy.csv" in duplicate[0] and original.name in duplicate[0], err
    assert len(err.strip().splitlines()) < 10, err
    for table in ("intrinsic", "fits", "segments"):
        assert pl.read_parquet(tmp_path / "one" / f"{table}.parquet").equals(pl.read_parquet(tmp_path / "two" / f"{table}.parquet"))
    # and a finding in the time-base table, which a batch publishes (it keeps no notes)
    found = pl.read_parquet(tmp_path / "two" / "timebase.parquet").filter(pl.col("check") == "duplicate_capture")
    assert found.select("capture", "detected").rows() == [("zz_copy.csv", True)]
    assert original.name in found["evidence"][0]
    assert pl.read_parquet(tmp_path / "one" / "timebase.parquet").filter(pl.col("check") == "duplicate_capture").is_empty()


def test_a_fifo_under_root_does_not_hang_the_batch(tmp_path):
    if not hasattr(os, "mkfifo"):
        pytest.skip("no FIFOs here")
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    os.mkfifo(root / "trap.csv")
    summary = run_batch(root, out, SERIAL)
    assert (summary.ok, summary.quarantined) == (1, 1)
    assert "trap.csv: not a regular file" in summary.problems[0]["reason"]


def test_what_dask_results_trust_is_documented():
    text = " ".join((REPO / "docs" / "batch.md").read_text().split())
    assert "results come back from Dask workers as pickles" in text
