"""A real ``rotcal batch`` process, one of whose pool workers is killed
(as the out-of-memory killer would) and which is then itself killed with
SIGKILL mid-run, and restarted: the same tables as an uninterrupted run, no
temporary or partial file, no orphan worker, and the work recorded before
the kill kept."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from rotcal.batch.runner import run_batch

from batch_support import (
    REPO,
    SERIAL,
    assert_clean,
    assert_same_tables,
    config_file,
    make_root,
    manifest_rows,
    result_tables,
    run_cli,
    summary_of,
)


def published(out: Path) -> int:
    try:
        return len(list((out / "datasets").iterdir()))
    except FileNotFoundError:
        return 0


def pool_workers(pid: int) -> set[int]:
    """The batch process's multiprocessing workers (not its resource tracker)."""
    found = set()
    for task in os.listdir(f"/proc/{pid}/task"):
        try:
            children = Path(f"/proc/{pid}/task/{task}/children").read_text().split()
        except FileNotFoundError:  # the thread ended since the listing (the pool's manager thread is replaced)
            continue
        for child in children:
            try:
                if b"spawn_main" in Path(f"/proc/{child}/cmdline").read_bytes():
                    found.add(int(child))
            except (FileNotFoundError, ProcessLookupError):  # the child ended between the listing and the read
                pass
    return found


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def wait_for(proc, condition, seconds: float = 90) -> None:
    deadline = time.monotonic() + seconds
    while not condition() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.005)
    assert proc.poll() is None and condition(), "the run ended, or stalled, before it could be killed"


def test_killed_worker_and_sigkilled_run_then_restart_give_the_uninterrupted_tables(tmp_path):
    root, ref, out = tmp_path / "root", tmp_path / "ref", tmp_path / "out"
    make_root(root, range(1, 13))
    run_batch(root, ref, SERIAL)  # one process, fit threads on every core
    config = config_file(tmp_path)

    proc = subprocess.Popen([sys.executable, "-m", "rotcal", "batch", root, "--out", out, "--workers", "2", "--config", config],
                            cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    workers: set[int] = set()

    def seen(count: int):
        def check() -> bool:
            workers.update(pool_workers(proc.pid))
            return published(out) >= count
        return check

    wait_for(proc, seen(2))
    os.kill(min(w for w in workers if alive(w)), signal.SIGKILL)  # its jobs fail; the pool is replaced
    wait_for(proc, seen(6))  # at most 4 jobs were lost with the worker: only a new pool gets here
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    time.sleep(0.3)
    assert len(workers) >= 3 and not [w for w in workers if alive(w)], "a pool worker outlived the killed run"

    recorded = manifest_rows(out)
    assert 0 < len(recorded) < 12
    errors = [r["reason"] for r in recorded.values() if r["status"] == "error"]
    assert errors and all(e.startswith("the worker failed: BrokenProcessPool") for e in errors), errors
    result = run_cli("batch", root, "--out", out, "--workers", "1", "--json", "--config", config)
    assert result.returncode == 0, result.stderr
    summary = summary_of(result.stdout)
    done = sum(r["status"] == "ok" for r in recorded.values())
    # What was recorded ok before the kill is kept; the rest (errors included) is done now.
    assert summary["ok"] == summary["processed"] == 12 - done and summary["unchanged"] == done
    assert_same_tables(result_tables(ref), result_tables(out))
    assert_clean(out)
    assert sorted(r["status"] for r in manifest_rows(out).values()) == ["ok"] * 12
