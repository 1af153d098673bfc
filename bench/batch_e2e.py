"""End to end, as a new user runs it: ``rotcal batch ROOT --out DIR
--workers W`` in a fresh process with the default configuration (the
diagnosis and its report.md, the certificate, no PNG figures: a batch draws
them only with --figures), over 100 default-plan CSV datasets (54,000
samples each), clean and a mix where two thirds carry one catalogue effect
(sizes drawn across each effect's range, as scripts/diagnosis_acceptance.py
does), against the floor of the same run: ``polars.read_csv`` of every
capture (reading the data at all).

Wall time depends on what else the machine runs; CPU time (the batch process
and its pool workers) much less, so both are printed, per dataset, with the
load average. ``--reference PYTHON`` runs another rotcal installation (an
interpreter whose ``-m rotcal`` is, say, the main branch) on the same
datasets in the same bench run, each run beside its reference, and prints
the ratios: on a shared machine the ratio is the figure to trust.
``--rounds N`` runs every batch N times on the same datasets, the two
rotcals in turn first (on the 2-core machine the one run first was several
percent slower, docs/measured.md, eleventh session), and ends with each
ratio's median.

    python bench/batch_e2e.py [--datasets 100] [--workers 2] [--reference /path/to/python] [--rounds 1] [--without-diagnosis]
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

# the environment a new user's shell gives rotcal batch, taken before Polars is
# imported here: Polars sets its allocator's variable (_RJEM_MALLOC_CONF) in
# this process's environment, which every child would otherwise inherit
NEW_USER_ENVIRONMENT = dict(os.environ)

import numpy as np  # noqa: E402
import polars as pl  # noqa: E402

from rotcal.diagnose.scenarios import draw_effect  # noqa: E402
from rotcal.model.effects import names  # noqa: E402
from rotcal.simulate import SimulationSpec, simulate, write_dataset  # noqa: E402


def effects_of(seed: int, mix: bool) -> tuple[str, ...]:
    """The mix: datasets whose seed is not a multiple of 3 carry one catalogue
    effect, the effects taken in turn, each size drawn across its range."""
    if not mix or seed % 3 == 0:
        return ()
    catalogue = names()
    return (draw_effect(catalogue[seed % len(catalogue)], np.random.default_rng([300, seed])),)


def _simulate(args: tuple[int, Path, bool]) -> None:
    seed, directory, mix = args
    spec = SimulationSpec().with_effects(*effects_of(seed, mix))
    write_dataset(simulate(spec, seed), spec, directory, "csv")


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def batch(python: str, root: Path, out: Path, workers: int, config: Path | None) -> tuple[float, float]:
    """Wall and CPU seconds (the batch process and its workers) of one fresh ``rotcal batch``."""
    command = [python, "-m", "rotcal", "batch", str(root), "--out", str(out), "--workers", str(workers)]
    cpu, start = _children_cpu(), time.perf_counter()
    run = subprocess.run(command + (["--config", str(config)] if config else []), capture_output=True, text=True,
                         env=NEW_USER_ENVIRONMENT)
    if run.returncode != 0:
        raise SystemExit(f"{' '.join(command)}: exit {run.returncode}\n{run.stderr[-2000:]}")
    return time.perf_counter() - start, _children_cpu() - cpu


# whether a rotcal's modules load from bytecode or are compiled from source in
# every process (an editable install where PYTHONDONTWRITEBYTECODE is set):
# about 0.1 s of CPU a process, the batch process's and each worker's
BYTECODE = ("import importlib.util, os, rotcal.run as m; "
            "print('bytecode' if os.path.exists(importlib.util.cache_from_source(m.__file__)) else 'no bytecode')")


def bytecode(python: str) -> str:
    return subprocess.run([python, "-c", BYTECODE], capture_output=True, text=True, env=NEW_USER_ENVIRONMENT).stdout.strip()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=100)
    parser.add_argument("--workers", type=int, default=2, help="rotcal batch --workers; 0 = one per core")
    parser.add_argument("--reference", help="python of another rotcal installation, run beside this one")
    parser.add_argument("--without-diagnosis", action="store_true", help="also run the clean datasets with [diagnosis] enabled = false")
    parser.add_argument("--rounds", type=int, default=1, help="runs of every batch, the rotcals in turn first")
    args = parser.parse_args()
    n = args.datasets
    pythons = [("this rotcal", sys.executable)] + ([("reference", args.reference)] if args.reference else [])
    with tempfile.TemporaryDirectory() as tmp:
        roots = {"clean": Path(tmp) / "clean", "mix": Path(tmp) / "mix"}
        jobs = [(seed, root / f"dut{seed:03d}", kind == "mix") for kind, root in roots.items() for seed in range(1, n + 1)]
        with ProcessPoolExecutor() as pool:
            list(pool.map(_simulate, jobs))
        os.sync()  # the datasets' pages written back now, not by the kernel's flusher during the first batch timed
        start = time.perf_counter()
        rows = sum(pl.read_csv(f).height for f in sorted(roots["clean"].rglob("*.csv")))
        floor = time.perf_counter() - start
        print(f"{n} datasets, {rows:,} samples; polars.read_csv of every capture: {floor:.2f} s; {os.cpu_count()} cores; "
              f"rotcal batch --workers {args.workers}, default configuration (report.md and certificate.html per dataset, "
              f"no PNG figures)", flush=True)
        print("rotcal's modules: " + "; ".join(f"{who}: {bytecode(python)}" for who, python in pythons), flush=True)
        no_diagnosis = Path(tmp) / "no_diagnosis.toml"
        no_diagnosis.write_text("[diagnosis]\nenabled = false\n")
        runs = [("clean", "clean datasets", None), ("mix", "two thirds with a catalogue effect", None)]
        if args.without_diagnosis:
            runs.insert(0, ("clean", "clean datasets, diagnosis off", no_diagnosis))
        ratios: dict[str, list[tuple[float, float]]] = {label: [] for _, label, _ in runs}
        for r in range(args.rounds):
            for k, (kind, label, config) in enumerate(runs):
                measured = {}
                for who, python in pythons if r % 2 == 0 else pythons[::-1]:
                    load = os.getloadavg()[0]
                    wall, cpu = batch(python, roots[kind], Path(tmp) / f"out{r}_{k}_{who[0]}", args.workers, config)
                    measured[who] = (wall, cpu)
                    print(f"{who}, {n} {label}: {wall:.1f} s wall ({60 * n / wall:.0f} datasets/minute, "
                          f"{wall / floor:.0f} x the read_csv floor), CPU {cpu:.1f} s = {cpu / n:.3f} s per dataset "
                          f"({60 * n / cpu:.0f} datasets per CPU-minute); load average {load:.1f} at the start", flush=True)
                if args.reference:
                    (wall, cpu), (ref_wall, ref_cpu) = measured["this rotcal"], measured["reference"]
                    ratios[label].append((ref_wall / wall, ref_cpu / cpu))
                    print(f"  {label}: this rotcal over the reference: {ref_wall / wall:.2f}x wall, {ref_cpu / cpu:.2f}x CPU", flush=True)
        if args.reference and args.rounds > 1:
            for label, pairs in ratios.items():
                print(f"{label}, median of {args.rounds} rounds: this rotcal over the reference "
                      f"{statistics.median(w for w, _ in pairs):.2f}x wall, {statistics.median(c for _, c in pairs):.2f}x CPU")


if __name__ == "__main__":
    main()
