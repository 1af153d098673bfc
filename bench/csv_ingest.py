"""CSV ingest, rows per second: rotcal's ``read_csv_capture`` (parsing plus
validation: line lengths, finite values, time order, labels, canonical
columns) against ``polars.read_csv`` of the same file, so the ratio shows
what validation costs.

    python bench/csv_ingest.py [--rotation-samples 80000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import polars as pl  # noqa: E402
from common import best_of, report  # noqa: E402

from rotcal.config import Limits  # noqa: E402
from rotcal.ingest.csv_source import read_csv_capture  # noqa: E402
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
        ours = best_of(lambda: read_csv_capture(path, CsvFormat(), None, Limits()), args.repeats)
        theirs = best_of(lambda: pl.read_csv(path), args.repeats)
        report(f"CSV ingest ({n:,} rows, {path.stat().st_size / 1e6:.0f} MB)", n, "rows", ours, "polars.read_csv", theirs)


if __name__ == "__main__":
    main()
