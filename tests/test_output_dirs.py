"""Issue 14, item 1: an output directory holds one run. A run is staged
beside its output directory, listed (rotcal-files.json) and swapped in
whole; only what a listing names is replaced without --replace; an unusable
--out is refused before any computation; simulate and demo likewise."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import jsonschema
import polars as pl
import pytest
from test_bad_input import assert_one_line_error

from rotcal.report.publish import LISTING, OutputDir, publish_directory
from rotcal_schemas import schema_text

from posesim import hand_placed, samples_frame
from testdata import REPO

DELAY = "channel_delay:delay_v_s=0.003,delay_w_s=0"


def _static_dataset(directory: Path, seed: int = 77, poses: int = 24) -> Path:
    """Hand-placed static poses (tests/posesim.py): no table segments; 8 poses are too few (exit 3)."""
    directory.mkdir(parents=True)
    samples_frame(hand_placed(seed, n_poses=poses, samples=300, move_samples=150)).write_csv(directory / "session.csv")
    (directory / "dataset.toml").write_text('[device]\noutput_unit = "count"\n\n[site]\ng_local = 9.80101\n')
    return directory


def _files(directory: Path) -> dict[str, tuple[int, str]]:
    """Every file under ``directory`` but its listing: (size, SHA-256) by relative name."""
    files = {p.relative_to(directory).as_posix(): p for p in directory.rglob("*") if p.is_file()}
    return {name: (p.stat().st_size, hashlib.sha256(p.read_bytes()).hexdigest()) for name, p in files.items() if name != LISTING}


def _listing(directory: Path) -> dict[str, tuple[int, str]]:
    doc = json.loads((directory / LISTING).read_text())
    jsonschema.validate(doc, schema_text("rotcal_files"))
    return {f["name"]: (f["bytes"], f["sha256"]) for f in doc["files"]}


def _not_computed(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("computed before the output directory was checked")

    monkeypatch.setattr("rotcal.run._run", fail)
    monkeypatch.setattr("rotcal.simulate.simulate", fail)


@pytest.fixture(scope="module")
def run_a(make_dataset, tmp_path_factory):
    """Run A's output: table segments with a channel delay, which the diagnosis finds."""
    from rotcal.run import run_dataset

    out = tmp_path_factory.mktemp("run_a") / "out"
    run_dataset(make_dataset(5, effects=(DELAY,)), out)
    return out


def test_a_run_into_an_earlier_runs_directory_leaves_only_its_own_files(cli, run_a, tmp_path):
    """Run A (table segments, channel delay found: report.md, figures/,
    frequency response) then run B (static poses) into one --out: every
    file there is B's, and the listing names exactly what is there."""
    assert "channel_delay" in set(pl.read_parquet(run_a / "diagnosis.parquet").filter("detected")["effect"])
    out = tmp_path / "out"
    shutil.copytree(run_a, out)
    a_files = _files(out)
    assert _listing(out) == a_files
    assert {"report.md", "frequency_response.png", "consistency.parquet"} <= set(a_files)
    assert any(name.startswith("figures/") for name in a_files)

    b = _static_dataset(tmp_path / "b")
    status, _, err = cli("run", b, "--out", out, "--quiet")
    assert status == 0, err
    b_files = _files(out)
    assert _listing(out) == b_files
    assert "poses.parquet" in b_files and not {"figures", "consistency.parquet"} & {n.split("/")[0] for n in b_files}
    assert "Static recording" in (out / "report.md").read_text()  # B's own diagnosis report (static poses are diagnosed)
    assert set(pl.read_parquet(out / "intrinsic.parquet")["dataset"]) == {"b"}
    assert not [n for n in b_files if n in a_files and a_files[n] == b_files[n]]  # nothing of A's survives as it was
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b", "out"]  # no staging or aside directory left


def test_an_undetermined_run_publishes_its_input_tables_alone(cli, run_a, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(run_a, out)
    # five poses: not even the six parameters of orthogonal axes are determined (seven needed)
    status, _, err = cli("run", _static_dataset(tmp_path / "c", seed=79, poses=5), "--out", out)
    assert status == 3, err
    assert set(_files(out)) == set(_listing(out)) == {"segments.parquet", "fits.parquet", "timebase.parquet", "poses.parquet"}
    # a static recording: no table segments, where A had its plan's
    assert pl.read_parquet(out / "segments.parquet").height == 0 < pl.read_parquet(run_a / "segments.parquet").height


def test_an_unusable_out_is_one_line_before_any_computation(cli, tmp_path, monkeypatch):
    _not_computed(monkeypatch)
    data = _static_dataset(tmp_path / "b")
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert_one_line_error(cli("run", data, "--out", a_file), "a_file", "is not a directory")
    assert_one_line_error(cli("run", data, "--out", a_file / "sub"), "a_file", "is not a directory")
    assert_one_line_error(cli("run", data, "--out", data), "holds the input")
    assert_one_line_error(cli("run", data, "--out", data.parent, "--replace"), "holds the input")
    assert_one_line_error(cli("simulate", a_file), "a_file", "is not a directory")
    locked, inside = tmp_path / "locked", tmp_path / "locked" / "out"
    inside.mkdir(parents=True)
    real = os.access  # as root the kernel lets every write through: answer as it would for another user
    monkeypatch.setattr(os, "access", lambda path, mode: real(path, mode) and not (Path(path) == locked and mode & os.W_OK))
    assert_one_line_error(cli("run", data, "--out", locked), "locked", "cannot be written")
    assert_one_line_error(cli("run", data, "--out", locked / "new"), "locked", "cannot be written")
    # a directory that may be written into, in a folder that may not: the swap renames it there
    assert_one_line_error(cli("run", data, "--out", inside), "out", "cannot be replaced", "locked cannot be written")
    assert_one_line_error(cli("demo", "--dir", inside), "cannot be replaced")


def test_the_refusal_loads_no_stage(tmp_path):
    """`rotcal run` with --out a file, in its own process: refused before
    the stages (scipy, polars) are imported; the time is the interpreter's
    and the command line's start."""
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    script = ("import sys, time; t = time.perf_counter(); from rotcal.cli import main; sys.argv = sys.argv[1:]\n"
              "try:\n    main()\nexcept SystemExit as e:\n"
              "    print(e.code, time.perf_counter() - t, *(m in sys.modules for m in ('scipy', 'polars', 'rotcal.run')))")
    clock = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", script, "rotcal", "run", str(REPO), "--out", str(a_file)],
                          capture_output=True, text=True, timeout=120)
    wall = time.perf_counter() - clock
    code, seconds, *loaded = done.stdout.split()
    assert code == "2" and loaded == ["False", "False", "False"], done.stdout + done.stderr
    assert done.stderr.count("\n") == 1 and "is not a directory" in done.stderr
    print(f"refusal: {float(seconds):.3f} s in main, {wall:.3f} s wall")


def test_files_no_listing_names_are_refused_unless_replaced(cli, tmp_path, monkeypatch):
    data = _static_dataset(tmp_path / "b")
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with monkeypatch.context() as m:
        _not_computed(m)
        assert_one_line_error(cli("run", data, "--out", out), "out", "no rotcal listing names", "notes.txt", "--replace")
    assert (out / "notes.txt").read_text() == "mine"
    out.chmod(0o750)
    status, _, err = cli("run", data, "--out", out, "--replace", "--quiet")
    assert status == 0, err
    assert "notes.txt" not in _files(out) and _listing(out) == _files(out)
    assert out.stat().st_mode & 0o777 == 0o750
    # rotcal's own listed files are replaced without being told; a file changed since, or added, is not
    assert cli("run", data, "--out", out, "--quiet")[0] == 0
    table = out / "intrinsic.parquet"
    with table.open("r+b") as f:  # one byte changed, the size kept: only the SHA-256 tells
        f.seek(100)
        byte = f.read(1)
        f.seek(100)
        f.write(bytes([byte[0] ^ 1]))
    assert_one_line_error(cli("run", data, "--out", out), "no rotcal listing names", "intrinsic.parquet")
    with table.open("ab") as f:
        f.write(b"\0")
    assert_one_line_error(cli("run", data, "--out", out), "no rotcal listing names", "intrinsic.parquet")
    assert cli("run", data, "--out", out, "--replace", "--quiet")[0] == 0
    (out / "figures").mkdir()
    assert_one_line_error(cli("run", data, "--out", out), "no rotcal listing names", "figures")


def test_a_killed_runs_staging_is_removed_by_the_next_run(cli, tmp_path):
    data = _static_dataset(tmp_path / "b")
    out = tmp_path / "out"
    dead = subprocess.Popen(["true"])  # a process that has ended: its pid names no process now
    dead.wait()
    alive = subprocess.Popen(["sleep", "60"])
    try:
        left = [tmp_path / f".out.rotcal-staging.{dead.pid}.0123abcd", tmp_path / f".out.rotcal-old.{dead.pid}.89abcdef"]
        running = tmp_path / f".out.rotcal-staging.{alive.pid}.fedcba98"  # another run, still writing
        for folder in (*left, running):
            (folder / "figures").mkdir(parents=True)
            (folder / "intrinsic.parquet").write_text("half written")
        assert cli("run", data, "--out", out, "--quiet")[0] == 0
        assert sorted(p.name for p in tmp_path.iterdir()) == sorted([running.name, "b", "out"])
        assert _listing(out) == _files(out)
    finally:
        alive.kill()
        alive.wait()


def test_a_failure_while_writing_leaves_the_old_output(tmp_path):
    out = tmp_path / "out"
    publish_directory(OutputDir(out), lambda staging: [_write(staging / "a.txt", "old")])

    def broken(staging: Path) -> list[Path]:
        _write(staging / "a.txt", "new")
        raise OSError(28, "No space left on device")

    with pytest.raises(OSError):
        publish_directory(OutputDir(out), broken)
    assert (out / "a.txt").read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def test_simulate_refuses_a_directory_that_is_not_empty(cli, tmp_path, monkeypatch):
    target = tmp_path / "sim"
    target.mkdir()
    (target / "old.csv").write_text("t,u,v,w\n")
    with monkeypatch.context() as m:
        _not_computed(m)
        assert_one_line_error(cli("simulate", target), "sim", "is not empty", "old.csv", "--replace")
    assert sorted(p.name for p in target.iterdir()) == ["old.csv"]
    small = tmp_path / "plan.toml"
    small.write_text("[plan]\nrates_hz = [0.5]\nstep_samples = 10\nrotation_samples = 200\n")
    assert cli("simulate", target, "--config", small, "--replace")[0] == 0
    files = sorted(p.name for p in target.iterdir())
    assert "old.csv" not in files and "dataset.toml" in files and "truth.json" in files and LISTING not in files
    assert json.loads((target / "truth.json").read_text())["plan"]["rates_hz"] == [0.5]
    assert 'id = "sim"' in (target / "dataset.toml").read_text()
    assert_one_line_error(cli("simulate", target, "--config", small), "is not empty")


def test_demo_replaces_its_own_folder(cli, tmp_path, monkeypatch):
    from batch_support import SMALL

    monkeypatch.setattr("rotcal.simulate.SimulationSpec", lambda: SMALL)  # the demo's steps on a small plan
    for seed in ("1", "2"):
        status, out, err = cli("demo", "--dir", tmp_path / "demo", "--seed", seed)
        assert status == 0, err
        assert f"tableswrittento{tmp_path / 'demo' / 'results'}:" in "".join(out.split())  # a long path is wrapped
    files = _files(tmp_path / "demo")
    assert _listing(tmp_path / "demo") == files and "results/rotcal-files.json" in files
    assert {"data/dataset.toml", "data/truth.json", "results/intrinsic.parquet"} <= set(files)
    assert json.loads((tmp_path / "demo" / "data" / "truth.json").read_text())["seed"] == 2
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo"]


def test_demo_refuses_a_folder_not_its_own(cli, tmp_path, monkeypatch):
    _not_computed(monkeypatch)
    (tmp_path / "thesis.tex").write_text("mine")
    assert_one_line_error(cli("demo", "--dir", tmp_path), "no rotcal listing names", "thesis.tex")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["thesis.tex"]


def test_batch_publishes_each_dataset_with_its_listing(tmp_path):
    from rotcal.batch.runner import run_batch

    from batch_support import SERIAL, make_root

    make_root(tmp_path / "root", [1, 2])
    out = tmp_path / "out"
    assert run_batch(tmp_path / "root", out, SERIAL).exit_status == 0
    folders = sorted((out / "datasets").iterdir())
    assert len(folders) == 2
    for folder in folders:
        assert _listing(folder) == _files(folder) and "intrinsic.parquet" in _files(folder)
