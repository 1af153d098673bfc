"""End to end: ``rotcal batch`` over 100 default-plan CSV datasets (about
54,000 samples each), datasets per minute, without and with the diagnosis
stage.

``rotcal batch`` is detected; where it is not available yet the script says
so and measures a stand-in instead: ``run.run_dataset`` on every dataset
over a pool of one process per core (what a batch runner does, minus its
bookkeeping), labelled as such.

    python bench/batch_e2e.py [--datasets 100] [--workers 0]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from pipeline.config import load_config
from pipeline.run import run_dataset
from pipeline.simulate import SimulationSpec, simulate, write_dataset


def _simulate(args: tuple[int, Path]) -> None:
    seed, directory = args
    spec = SimulationSpec()
    write_dataset(simulate(spec, seed), spec, directory, "csv")


def _run(args: tuple[Path, Path, Path | None]) -> None:
    dataset, out, config = args
    run_dataset(dataset, out, None, load_config(config))


def batch_available() -> bool:
    probe = subprocess.run([sys.executable, "-m", "pipeline", "batch", "--help"], capture_output=True)
    return probe.returncode == 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=100)
    parser.add_argument("--workers", type=int, default=0, help="stand-in pool size; 0 = one per core")
    args = parser.parse_args()
    workers = args.workers or os.cpu_count() or 1
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "datasets"
        jobs = [(seed, root / f"dut{seed:03d}") for seed in range(1, args.datasets + 1)]
        with ProcessPoolExecutor(workers) as pool:
            list(pool.map(_simulate, jobs))
        no_diagnosis = Path(tmp) / "no_diagnosis.toml"
        no_diagnosis.write_text("[diagnosis]\nenabled = false\n")
        available = batch_available()
        if not available:
            print("rotcal batch: not available yet; measuring the stand-in (run_dataset over a process pool)")
        for label, config in (("without diagnosis", no_diagnosis), ("with diagnosis", None)):
            out = Path(tmp) / f"out_{label.split()[0]}"
            start = time.perf_counter()
            if available:
                command = [sys.executable, "-m", "pipeline", "batch", str(root), "--out", str(out)]
                subprocess.run(command + (["--config", str(config)] if config else []), check=True, capture_output=True)
                what = "rotcal batch"
            else:
                with ProcessPoolExecutor(workers) as pool:
                    list(pool.map(_run, [(d, out / d.name, config) for _, d in jobs]))
                what = f"stand-in, {workers} processes"
            seconds = time.perf_counter() - start
            print(f"end to end ({what}), {args.datasets} datasets {label}: {seconds:.1f} s, "
                  f"{60 * args.datasets / seconds:.0f} datasets/minute", flush=True)


if __name__ == "__main__":
    main()
