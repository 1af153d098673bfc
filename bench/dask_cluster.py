"""``rotcal batch`` beyond one process: the same default-plan CSV datasets run
on one worker, on the local pool, on a dask.distributed ``LocalCluster`` (2
workers x 1 thread) and on a cluster started as a site starts one (``dask
scheduler`` and two ``dask worker --nthreads 1``, separate processes, on
free ports of this machine); each run's speed-up against the single worker,
and whether every Parquet file it wrote is identical, byte for byte, to the
single worker's.

    python bench/dask_cluster.py [--datasets 40] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from batch_e2e import _simulate  # noqa: E402
from distributed import Client, LocalCluster  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextmanager
def local_cluster(workers: int) -> Iterator[str]:
    with LocalCluster(n_workers=workers, threads_per_worker=1, host="127.0.0.1", dashboard_address=None) as cluster:
        yield cluster.scheduler_address.removeprefix("tcp://")


@contextmanager
def process_cluster(workers: int) -> Iterator[str]:
    """``dask scheduler`` and ``workers`` x ``dask worker --nthreads 1``, as separate processes."""
    address = f"127.0.0.1:{_free_port()}"
    dask = str(Path(sys.executable).with_name("dask"))  # the command a site runs, from this environment
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    scheduler = subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", address.split(":")[1],
                                  "--dashboard-address", ":0"], **quiet)
    started = [scheduler] + [
        subprocess.Popen([dask, "worker", f"tcp://{address}", "--nthreads", "1", "--no-dashboard", "--host", "127.0.0.1"],
                         **quiet)
        for _ in range(workers)
    ]
    try:
        with Client(f"tcp://{address}", timeout="60s") as client:
            client.wait_for_workers(workers, timeout=120)
        yield address
    finally:
        for process in reversed(started):
            process.terminate()
        for process in started:
            process.wait(timeout=30)


def batch(root: Path, out: Path, *options: str) -> float:
    """Wall seconds of one ``rotcal batch`` run."""
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rotcal", "batch", str(root), "--out", str(out), *options],
                   check=True, capture_output=True)
    return time.perf_counter() - start


def parquet_files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*.parquet"))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=40)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "datasets"
        with ProcessPoolExecutor() as pool:
            list(pool.map(_simulate, [(seed, root / f"dut{seed:03d}", False) for seed in range(1, args.datasets + 1)]))
        print(f"{args.datasets} default-plan CSV datasets, {args.workers} workers; load average "
              f"{os.getloadavg()[0]:.1f} at the start", flush=True)
        single = batch(root, Path(tmp) / "single", "--workers", "1")
        reference = parquet_files(Path(tmp) / "single")
        print(f"single worker (--workers 1): {single:.1f} s, {len(reference)} Parquet files", flush=True)
        runs = {
            f"local pool (--workers {args.workers})": lambda out: batch(root, out, "--workers", str(args.workers)),
            f"LocalCluster, {args.workers} workers x 1 thread": lambda out: _on(local_cluster, args.workers, root, out),
            f"dask scheduler + {args.workers} x dask worker --nthreads 1 (separate processes)":
                lambda out: _on(process_cluster, args.workers, root, out),
        }
        for k, (what, run) in enumerate(runs.items()):
            out = Path(tmp) / f"run{k}"
            seconds = run(out)
            files = parquet_files(out)
            differ = sorted(name for name in reference.keys() | files.keys() if reference.get(name) != files.get(name))
            print(f"{what}: {seconds:.1f} s, speed-up {single / seconds:.2f}x; {len(files)} Parquet files, "
                  f"{'all identical' if not differ else f'{len(differ)} differ: ' + ', '.join(differ[:5])}", flush=True)


def _on(cluster, workers: int, root: Path, out: Path) -> float:
    """``rotcal batch --executor dask://...`` on a fresh cluster (its start not timed)."""
    with cluster(workers) as address:
        return batch(root, out, "--executor", f"dask://{address}")


if __name__ == "__main__":
    main()
