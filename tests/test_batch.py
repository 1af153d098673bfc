"""rotcal batch: discovery and names, incremental runs judged by content,
the run lock, and the manifest's contract."""

import json
import os
import sqlite3
from dataclasses import replace

import jsonschema

from rotcal.batch.manifest import run_lock
from rotcal.batch.plan import dataset_id, discover
from rotcal.batch.runner import run_batch
from rotcal.config import BatchConfig, RunConfig
from rotcal.simulate import simulate, write_dataset
from rotcal_schemas import schema_text

from batch_support import SERIAL, SMALL, assert_clean, assert_same_tables, config_file, make_root, manifest_rows, result_tables


def test_dataset_ids_are_unique_safe_and_readable():
    assert dataset_id("lab1/DUT-7") == "lab1__DUT-7"
    assert dataset_id("single.mcap") == "single.mcap"
    tricky = ["a/b", "a__b", "a_/b", "a/_b", "a b/c", "a_b/c", "a/b_c", "été/x", "x" * 300, "x" * 299 + "y", "-"]
    ids = [dataset_id(p) for p in tricky]
    assert len(set(ids)) == len(tricky)
    for name in ids:
        assert name and len(name) <= 200 and "/" not in name and not name.startswith(".")
        assert all(c.isascii() and (c.isalnum() or c in "._-~") for c in name), name


def test_discovery_rules(tmp_path):
    root, out = tmp_path / "root", tmp_path / "root" / "results"
    make_root(root, [1, 4])  # lot1/dut001, lot1/dut004: directories with dataset.toml
    (root / "loose").mkdir()
    for name in ("a.csv", "b.MCAP", "notes.txt", ".hidden.csv"):
        (root / "loose" / name).write_text("x")
    (root / "lot1" / "dut001" / "sub").mkdir()
    (root / "lot1" / "dut001" / "sub" / "inner.csv").write_text("x")  # inside a dataset: not a dataset
    (root / "other" / "lot1").mkdir(parents=True)
    (root / "other" / "lot1" / "dut001.csv").write_text("x")  # same stem elsewhere
    (root / ".git").mkdir()
    (root / ".git" / "x.csv").write_text("x")
    (root / "results" / "datasets").mkdir(parents=True)
    (root / "results" / "datasets" / "y.csv").write_text("x")
    (root / "linked").symlink_to(root / "lot1")
    found = [f.dataset_path for f in discover(root, out)]
    assert found == ["linked", "loose/a.csv", "loose/b.MCAP", "lot1/dut001", "lot1/dut004", "other/lot1/dut001.csv"]
    assert len({dataset_id(p) for p in found}) == len(found)


def hash_times(out):
    with sqlite3.connect(out / "manifest.sqlite") as db:
        return dict(db.execute("SELECT path, hashed_at_ns FROM batch_file_hashes"))


def test_second_run_does_nothing_and_a_change_reprocesses_exactly_its_dataset(tmp_path, monkeypatch):
    # Files are only minutes old in a test: trust the cache at once, so that
    # what detects the change below is the stat comparison, not the racy rule.
    monkeypatch.setattr("rotcal.batch.manifest.RACY_NS", 0)
    root, out = tmp_path / "root", tmp_path / "out"
    paths = make_root(root, range(1, 7))
    first = run_batch(root, out, SERIAL)
    assert (first.discovered, first.processed, first.ok, first.exit_status) == (6, 6, 6, 0)
    before, rows, hashed = result_tables(out), manifest_rows(out), hash_times(out)

    second = run_batch(root, out, SERIAL)
    assert (second.processed, second.unchanged, second.exit_status) == (0, 6, 0)
    assert manifest_rows(out) == rows  # nothing was re-recorded
    assert hash_times(out) == hashed  # and nothing read again
    assert_clean(out)

    # Same content, new times: hashed again, found equal, nothing processed.
    target = sorted((root / paths[2]).glob("*_0.5hz.csv"))[0]
    os.utime(target, ns=(1, 1))
    assert run_batch(root, out, SERIAL).processed == 0

    # New content with the size and mtime restored: the ctime still moves.
    st = target.stat()
    text = target.read_text()
    last = text.rstrip("\n").rsplit("\n", 1)[1].split(",")
    last[1] = str(int(last[1]) + 1 if int(last[1]) < 9 else int(last[1]) - 1)  # u of the last sample, same width
    target.write_text(text.rstrip("\n").rsplit("\n", 1)[0] + "\n" + ",".join(last) + "\n")
    os.utime(target, ns=(st.st_atime_ns, st.st_mtime_ns))
    assert target.stat().st_size == st.st_size
    third = run_batch(root, out, SERIAL)
    assert (third.processed, third.ok, third.unchanged) == (1, 1, 5)
    assert [p for p, t in hash_times(out).items() if t != hashed[p]] == [str(target)]
    after = manifest_rows(out)
    assert [p for p in paths if after[p]["run_id"] != rows[p]["run_id"]] == [paths[2]]
    changed = {k for k, v in result_tables(out).items() if not v.equals(before[k])}
    assert changed and all(paths[2].replace("/", "__") in k for k in changed)

    # A configuration the results depend on re-processes everything.
    limits = replace(SERIAL.limits, max_line_bytes=SERIAL.limits.max_line_bytes + 1)
    assert run_batch(root, out, replace(SERIAL, limits=limits)).processed == 6
    assert_clean(out)


def test_a_file_changed_just_before_it_was_hashed_is_hashed_again(tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    run_batch(root, out, SERIAL)
    hashed = hash_times(out)
    run_batch(root, out, SERIAL)  # its ctime is within RACY_NS of the first hashing
    assert all(t > hashed[p] for p, t in hash_times(out).items())


def test_a_dataset_that_changes_to_bad_is_withdrawn_and_one_that_heals_returns(tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    paths = make_root(root, [1, 2])
    run_batch(root, out, SERIAL)
    toml = root / paths[0] / "dataset.toml"
    good = toml.read_text()
    toml.write_text(good + "\nnot toml\n")
    bad = run_batch(root, out, SERIAL)
    assert (bad.quarantined, bad.exit_status) == (1, 4)
    assert "dataset.toml is not valid TOML" in bad.problems[0]["reason"]
    assert not (out / "datasets" / dataset_id(paths[0])).exists()
    assert set(result_tables(out)) == {k for k in result_tables(out) if dataset_id(paths[1]) in k}
    again = run_batch(root, out, SERIAL)  # unchanged: not retried, still reported
    assert (again.processed, again.still_quarantined, again.exit_status) == (0, 1, 4)
    toml.write_text(good)
    healed = run_batch(root, out, SERIAL)
    assert (healed.processed, healed.ok, healed.exit_status) == (1, 1, 0)
    assert (out / "datasets" / dataset_id(paths[0]) / "intrinsic.parquet").is_file()
    assert_clean(out)


def test_results_of_a_dataset_removed_from_root_are_kept(tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    paths = make_root(root, [1, 2])
    run_batch(root, out, SERIAL)
    (root / paths[0]).rename(tmp_path / "archived")
    summary = run_batch(root, out, SERIAL)
    assert (summary.processed, summary.not_found) == (0, 1)
    assert len(list((out / "combined" / "intrinsic").glob("*.parquet"))) == 2


def test_a_live_lock_stops_a_second_run_and_a_stale_one_is_taken_over(cli, tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    out.mkdir()
    with run_lock(out):
        status, stdout, err = cli("batch", root, "--out", out)
    assert status == 5
    assert len(err.strip().splitlines()) == 1 and "another batch run holds the lock (pid" in err
    (out / "batch.lock").write_text("pid 999999 on somewhere since 2026-01-01T00:00:00Z\n")  # left by a killed run
    status, stdout, err = cli("batch", root, "--out", out, "--workers", "1", "--json", "--config", config_file(tmp_path))
    assert status == 0, err
    summary = json.loads(stdout)
    assert summary["ok"] == 1 and "stale lock" in summary["notes"][0] and "pid 999999" in summary["notes"][0]
    assert (out / "batch.lock").read_text() == ""


def test_an_unreadable_manifest_is_a_one_line_error_and_moving_it_away_recovers(cli, tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    run_batch(root, out, SERIAL)
    before = result_tables(out)
    (out / "manifest.sqlite").write_bytes(b"not a database" * 100)
    status, _, err = cli("batch", root, "--out", out)
    assert status == 1 and len(err.strip().splitlines()) == 1 and "the manifest cannot be read" in err
    assert (out / "batch.lock").read_text() == ""  # an error is not a dead run
    (out / "manifest.sqlite").unlink()
    assert run_batch(root, out, SERIAL).ok == 1
    assert_same_tables(before, result_tables(out))
    assert_clean(out)


def test_manifest_tables_follow_their_contracts(tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    (root / "broken.csv").write_text("t,u\n0,1\n")
    (root / "gone.csv").symlink_to(root / "nowhere.csv")
    (root / os.fsdecode(b"caf\xe9.csv")).write_text("t,u,v,w\n")
    summary = run_batch(root, out, RunConfig(batch=BatchConfig(workers=1)))  # every default stage, the report too
    reasons = {p["dataset_path"]: p["reason"] for p in summary.problems}
    assert reasons["gone.csv"].endswith("gone.csv: cannot be read: No such file or directory")
    assert reasons["caf\\xe9.csv"] == "caf\\xe9.csv: the path is not valid UTF-8 (rename it)"
    jsonschema.validate(summary.as_dict(), schema_text("batch_summary"))
    with sqlite3.connect(out / "manifest.sqlite") as db:
        for table in ("batch_datasets", "batch_runs", "batch_file_hashes"):
            columns = [r[1] for r in db.execute(f"PRAGMA table_info({table})")]
            assert columns == [c["name"] for c in schema_text(table)["columns"]]
        run = db.execute("SELECT finished_at, summary FROM batch_runs").fetchone()
    assert run[0] and json.loads(run[1])["quarantined"] == 3
    rows = manifest_rows(out)
    assert rows["broken.csv"]["status"] == "quarantined" and "missing required column" in rows["broken.csv"]["reason"]
    ok = rows["lot1/dut001"]
    assert ok["status"] == "ok" and ok["reason"] is None and ok["duration_s"] > 0
    inputs = dict(json.loads(ok["inputs"]))
    assert set(inputs) == {f"lot1/dut001/{p.name}" for p in (root / "lot1/dut001").iterdir() if p.name != "truth.json"}
    assert json.loads(ok["config"])["limits"]["max_line_bytes"] == SERIAL.limits.max_line_bytes
    # Whatever run_dataset writes is published; every Parquet table is combined.
    published = out / "datasets" / ok["dataset_id"]
    tables = json.loads(ok["tables"])
    assert {"intrinsic", "fits", "diagnosis"} <= set(tables) and (published / "report.md").is_file()
    assert sorted(p.name for p in (out / "combined").iterdir()) == sorted(tables)
    assert sorted(p.stem for p in published.glob("*.parquet")) == sorted(tables)
    assert_clean(out)


def test_bad_root_and_executor_are_one_line_errors(cli, tmp_path):
    write_dataset(simulate(SMALL, 1), SMALL, tmp_path / "dut")
    for args, needle in (((tmp_path / "nowhere",), "ROOT is not a directory"),
                         ((tmp_path / "dut",), "ROOT is itself a dataset"),
                         ((tmp_path, "--executor", "spark://x"), "is not 'local' or 'dask://HOST:PORT'")):
        status, _, err = cli("batch", *args, "--out", tmp_path / "out")
        assert status == 2 and len(err.strip().splitlines()) == 1 and needle in err, err


def test_plain_log_lines_when_not_on_a_terminal(cli, tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1, 2])
    (root / "bad.csv").write_text("nothing useful\n")
    status, stdout, err = cli("batch", root, "--out", out, "--workers", "1", "--config", config_file(tmp_path))
    assert status == 4
    lines = err.strip().splitlines()
    assert "rotcal batch: 3 datasets found: 0 unchanged, 3 to process" in lines[0]
    assert sorted(line.split("] ", 1)[1].split(" (")[0] for line in lines[1:]) == [
        "ok lot1/dut001", "ok lot2/dut002", "quarantined bad.csv"]
    assert "3 datasets: 3 processed (2 ok, 1 quarantined, 0 errors)" in stdout


def test_batch_draws_figures_only_when_asked_and_the_switch_reprocesses(cli, tmp_path):
    """Figures are for people: a batch writes tables (and the diagnosis
    report) unless --figures; the switch is part of what results depend on."""
    root, out = tmp_path / "root", tmp_path / "out"
    make_root(root, [1])
    status, _, err = cli("batch", root, "--out", out, "--workers", "1")
    assert status == 0, err
    published = out / "datasets" / "lot1__dut001"
    assert (published / "intrinsic.parquet").exists() and (published / "report.md").exists()
    assert not list(published.rglob("*.png")) and "## Figures" not in (published / "report.md").read_text()
    status, stdout, err = cli("batch", root, "--out", out, "--workers", "1", "--figures", "--json")
    assert status == 0, err
    assert json.loads(stdout)["processed"] == 1
    assert (published / "frequency_response.png").read_bytes()[:4] == b"\x89PNG"
    assert "## Figures" in (published / "report.md").read_text()
