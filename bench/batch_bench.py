"""Measures rotcal batch on the standard machine (figures in docs/measured.md):
throughput on N default-plan datasets with 1 and 2 workers, the no-op run's
wall time, re-processing after one changed file, and a CSV with a
multi-gigabyte line refused in bounded memory.

    .venv/bin/python bench/batch_bench.py [--datasets 100] [--dir /tmp/rotcal-bench]

Each run is a real ``rotcal batch`` subprocess; wall times include its
start-up (about 0.7 s of imports).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from batch_e2e import NEW_USER_ENVIRONMENT  # noqa: E402  (first: taken before Polars is imported)

from rotcal.simulate import SimulationSpec, simulate, write_dataset  # noqa: E402


def batch(root: Path, out: Path, *args: str) -> tuple[float, dict, int, float]:
    """Wall time, JSON summary, peak RSS (MB; the batch process itself, not
    its pool workers) and CPU time (user + system, s; with its workers) of
    one ``rotcal batch``."""
    start = time.perf_counter()
    run = subprocess.run(["/usr/bin/time", "-f", "%M %U %S", sys.executable, "-m", "rotcal", "batch", str(root),
                          "--out", str(out), "--json", *args], capture_output=True, text=True, env=NEW_USER_ENVIRONMENT)
    wall = time.perf_counter() - start
    if run.returncode not in (0, 4):
        raise SystemExit(run.stderr)
    rss, user, system = run.stderr.strip().splitlines()[-1].split()
    return wall, json.loads(run.stdout), int(rss) // 1024, float(user) + float(system)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--datasets", type=int, default=100)
    parser.add_argument("--dir", type=Path, default=Path("/tmp/rotcal-bench"))
    opts = parser.parse_args()
    shutil.rmtree(opts.dir, ignore_errors=True)
    root = opts.dir / "root"
    spec = SimulationSpec()  # the default plan: 3 axes x (steps + 4 rates), 54,000 samples
    for seed in range(1, opts.datasets + 1):
        write_dataset(simulate(spec, seed), spec, root / f"lot{seed % 4}" / f"dut{seed:04d}")
    size = sum(f.stat().st_size for f in root.rglob("*") if f.is_file())
    print(f"{opts.datasets} default-plan datasets, {size / 1e6:.0f} MB, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.1f}")

    rates = {}
    for workers in ("1", "2"):
        wall, summary, _, seconds = batch(root, opts.dir / f"out{workers}", "--workers", workers)
        assert summary["ok"] == opts.datasets, summary
        rates[workers] = opts.datasets / wall * 60
        print(f"first run, --workers {workers}: {wall:.1f} s wall, {rates[workers]:.0f} datasets/min; "
              f"CPU {seconds:.1f} s = {seconds / opts.datasets:.2f} s per dataset")
    print(f"speed-up of 2 workers over 1: {rates['2'] / rates['1']:.2f}")

    out = opts.dir / "out2"
    noop, cpu = [], []
    for _ in range(5):
        wall, summary, _, seconds = batch(root, out)
        assert summary["processed"] == 0, summary
        noop.append(wall)
        cpu.append(seconds)
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "rotcal", "--help"], capture_output=True)
    print(f"no-op run ({opts.datasets} datasets unchanged): median {statistics.median(noop):.2f} s wall "
          f"(min {min(noop):.2f}, max {max(noop):.2f}), median CPU {statistics.median(cpu):.2f} s; "
          f"`rotcal --help` alone: {time.perf_counter() - start:.2f} s wall")

    victim = sorted((root / "lot1" / "dut0001").glob("*.csv"))[0]
    lines = victim.read_text().split("\n")
    fields = lines[1].split(",")
    fields[1] = str(int(fields[1]) + 1)
    lines[1] = ",".join(fields)
    victim.write_text("\n".join(lines))
    wall, summary, one_peak, _ = batch(root, out)
    print(f"one file changed: {summary['processed']} dataset processed in the batch process, {wall:.2f} s wall, "
          f"peak RSS {one_peak} MB")

    hostile = opts.dir / "hostile"
    hostile.mkdir()
    with (hostile / "long_line.csv").open("wb") as fh:
        fh.write(b"t,u,v,w\n")
        fh.truncate(4 << 30)  # a 4 GiB line (sparse)
    wall, summary, peak, _ = batch(hostile, opts.dir / "out_hostile", "--workers", "1")
    print(f"4 GiB CSV line: {summary['problems'][0]['reason'].split(': ', 1)[1]}; {wall:.1f} s wall, "
          f"peak RSS {peak} MB (one default dataset processed the same way: {one_peak} MB)")


if __name__ == "__main__":
    main()
