"""CSV ingest, rows per second: rotcal's ``read_csv_capture`` (parsing plus
validation: line lengths, finite values, time order, labels, canonical
columns) against ``polars.read_csv`` of the same file, so the ratio shows
what validation costs; by the wall clock and by CPU time (the machine may
be shared).

    python bench/csv_ingest.py [--rotation-samples 80000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import polars as pl  # noqa: E402
from common import best_cpu_of, best_of, report  # noqa: E402

from rotcal.config import Limits  # noqa: E402
from rotcal.ingest.formats.csv.reader import read_csv_capture  # noqa: E402
from rotcal.ingest.meta import CsvFormat  # noqa: E402
from rotcal.simulate import Plan, SimulationSpec, simulate, write_csv_single  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotation-samples", type=int, default=80000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    sim = simulate(SimulationSpec(plan=Plan(rotation_samples=args.rotation_samples)), 1)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_csv_single(sim, Path(tmp) / "capture.csv", ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg"))
        n = pl.read_csv(path).height
        what = f"CSV ingest ({n:,} rows, {path.stat().st_size / 1e6:.0f} MB)"
        ours, theirs = (lambda: read_csv_capture(path, CsvFormat(), None, Limits())), (lambda: pl.read_csv(path))
        report(what, n, "rows", best_of(ours, args.repeats), "polars.read_csv", best_of(theirs, args.repeats))
        report(f"{what}, per CPU second", n, "rows", best_cpu_of(ours, args.repeats), "polars.read_csv",
               best_cpu_of(theirs, args.repeats))


if __name__ == "__main__":
    main()
