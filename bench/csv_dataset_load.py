"""A batch worker's ingest of default-plan CSV datasets (15 captures,
54,000 samples each): ``ingest.dataset.load_dataset`` (listing, metadata, copies,
parsing, validation, labels, time order) against ``polars.read_csv`` of the
same files one by one, on one polars thread as ``rotcal batch`` workers run;
milliseconds per dataset by the wall clock and by CPU time (the machine may
be shared), clean datasets and a mix where two thirds carry a catalogue effect.

    python bench/csv_dataset_load.py [--datasets 10] [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("POLARS_MAX_THREADS", "1")  # before polars is imported: a batch worker's setting

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from collections.abc import Callable  # noqa: E402
from functools import partial  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import polars as pl  # noqa: E402
from batch_e2e import _simulate  # noqa: E402
from common import best_cpu_of, best_of  # noqa: E402

from rotcal.ingest.dataset import load_dataset  # noqa: E402


def _each(read: Callable[[Path], object], paths: list[Path]) -> None:
    for path in paths:
        read(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        for kind, mix in (("clean", False), ("mix", True)):
            paths = [Path(tmp) / kind / f"d{s:03d}" for s in range(1, args.datasets + 1)]
            for seed, path in enumerate(paths, 1):
                _simulate((seed, path, mix))
            files = [sorted(p.glob("*.csv")) for p in paths]
            ours = partial(_each, load_dataset, paths)
            theirs = partial(_each, pl.read_csv, [f for fs in files for f in fs])
            per = 1000 / len(paths)
            for clock, best in (("wall", best_of), ("CPU", best_cpu_of)):
                a, b = best(ours, args.repeats) * per, best(theirs, args.repeats) * per
                print(f"{kind} default-plan CSV dataset, {clock}: load_dataset {a:.1f} ms; polars.read_csv of its "
                      f"{len(files[0])} files {b:.1f} ms; ratio {b / a:.2f}x", flush=True)


if __name__ == "__main__":
    main()
