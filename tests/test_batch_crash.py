"""A real ``rotcal batch`` process killed with SIGKILL mid-run, twice, then
restarted: the same tables as an uninterrupted run, no temporary or partial
file, no orphan worker, and the work recorded before the kills kept."""

import os
import signal
import subprocess
import sys
import time

from batch_support import REPO, assert_clean, assert_same_tables, make_root, manifest_rows, result_tables, run_cli, summary_of

from pipeline.batch import run_batch
from pipeline.config import BatchConfig, RunConfig


def published(out) -> int:
    try:
        return len(list((out / "datasets").iterdir()))
    except FileNotFoundError:
        return 0


def children(pid: int) -> set[int]:
    found = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        with open(f"/proc/{pid}/task/{task}/children") as fh:
            found |= {int(c) for c in fh.read().split()}
    return found


def alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def test_sigkill_mid_run_then_restart_gives_the_uninterrupted_tables(tmp_path):
    root, ref, out = tmp_path / "root", tmp_path / "ref", tmp_path / "out"
    make_root(root, range(1, 13))
    run_batch(root, ref, RunConfig(batch=BatchConfig(workers=1)))  # one process, fit threads on every core

    for target in (3, 7):
        proc = subprocess.Popen([sys.executable, "-m", "pipeline", "batch", root, "--out", out, "--workers", "2"],
                                cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline, workers = time.monotonic() + 60, set()
        while published(out) < target and proc.poll() is None and time.monotonic() < deadline:
            workers |= children(proc.pid)
            time.sleep(0.005)
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
        time.sleep(0.3)
        assert workers and not [w for w in workers if alive(w)], "a pool worker outlived the killed run"

    recorded = manifest_rows(out)
    assert 0 < len(recorded) < 12
    result = run_cli("batch", root, "--out", out, "--workers", "2", "--json")
    assert result.returncode == 0, result.stderr
    summary = summary_of(result.stdout)
    # Only what was not recorded before the last kill is processed again.
    assert summary["ok"] == summary["processed"] == 12 - len(recorded) and summary["unchanged"] == len(recorded)
    assert_same_tables(result_tables(ref), result_tables(out))
    assert_clean(out)
    assert sorted(r["status"] for r in manifest_rows(out).values()) == ["ok"] * 12
