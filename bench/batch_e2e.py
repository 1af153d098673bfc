"""End to end: ``rotcal batch`` over 100 default-plan CSV datasets (about
54,000 samples each), datasets per minute, without and with the diagnosis
stage, each against the floor of the same run: ``polars.read_csv`` of every
capture (reading the data at all).

Wall time depends on what else the machine runs; CPU time (the batch process
and its workers) does not, so both are printed with the load average.

    python bench/batch_e2e.py [--datasets 100] [--workers 0]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import polars as pl

from rotcal.simulate import SimulationSpec, simulate, write_dataset


def _simulate(args: tuple[int, Path]) -> None:
    seed, directory = args
    spec = SimulationSpec()
    write_dataset(simulate(spec, seed), spec, directory, "csv")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=100)
    parser.add_argument("--workers", type=int, default=0, help="rotcal batch --workers; 0 = one per core")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "datasets"
        jobs = [(seed, root / f"dut{seed:03d}") for seed in range(1, args.datasets + 1)]
        with ProcessPoolExecutor() as pool:
            list(pool.map(_simulate, jobs))
        start = time.perf_counter()
        rows = sum(pl.read_csv(f).height for f in sorted(root.rglob("*.csv")))
        floor = time.perf_counter() - start
        print(f"{args.datasets} datasets, {rows:,} samples; polars.read_csv of every capture: {floor:.2f} s", flush=True)
        no_diagnosis = Path(tmp) / "no_diagnosis.toml"
        no_diagnosis.write_text("[diagnosis]\nenabled = false\n")
        for label, config in (("without diagnosis", no_diagnosis), ("with diagnosis", None)):
            out = Path(tmp) / f"out_{label.split()[0]}"
            command = [sys.executable, "-m", "rotcal", "batch", str(root), "--out", str(out), "--workers", str(args.workers)]
            load, cpu, start = os.getloadavg()[0], _children_cpu(), time.perf_counter()
            subprocess.run(command + (["--config", str(config)] if config else []), check=True, capture_output=True)
            seconds, cpu = time.perf_counter() - start, _children_cpu() - cpu
            print(f"rotcal batch, {args.datasets} datasets {label}: {seconds:.1f} s wall "
                  f"({60 * args.datasets / seconds:.0f} datasets/minute, {seconds / floor:.0f} x the read_csv floor), "
                  f"CPU {cpu:.1f} s = {cpu / args.datasets:.2f} s per dataset; load average {load:.1f} at the start",
                  flush=True)


if __name__ == "__main__":
    main()
