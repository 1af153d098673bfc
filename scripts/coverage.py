"""Measure the coverage of rotcal's standard uncertainties on simulated clean
datasets (issue 3): for every intrinsic parameter, pooled over rates, the
fraction of |estimate - truth| <= 2 u must lie in the 99.9 % binomial
interval around 95.45 % and the RMS of z = (estimate - truth) / u in its
chi^2 interval around 1 (``tests/uncertainty_coverage.py``).

    python scripts/coverage.py --datasets 200 --workers 2

Prints a Markdown table (for docs/measured.md) and exits 1 if a parameter
fails. ``--effect`` and ``--sine-fit`` measure coverage under a physics effect
with the method meant for it, e.g. ``--effect rate_error:rate_error=2e-4
--sine-fit four_parameter``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from rotcal.config import FitConfig
from rotcal.simulate import SimulationSpec

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from uncertainty_coverage import coverage_frame, simulate_errors  # noqa: E402 (test support, beside the tests)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=200)
    parser.add_argument("--first-seed", type=int, default=10_000)
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--effect", action="append", default=[], help="NAME:key=value,... as for rotcal simulate")
    parser.add_argument("--sine-fit", default="three_parameter", choices=["three_parameter", "four_parameter"])
    args = parser.parse_args()
    spec = SimulationSpec().with_effects(*args.effect)
    start = time.perf_counter()
    z = simulate_errors(args.datasets, args.first_seed, spec, FitConfig(sine_fit=args.sine_fit), args.workers)
    frame = coverage_frame(z)
    print(f"{args.datasets} datasets (seeds {args.first_seed}..{args.first_seed + args.datasets - 1}), "
          f"{z.shape[1]} rates each, effects {args.effect or 'none'}, {args.sine_fit} sine fit; "
          f"{time.perf_counter() - start:.0f} s")
    low, high = frame["interval_low"][0], frame["interval_high"][0]
    print(f"\nacceptance intervals ({frame['trials'][0]} trials): within 2u {100 * low:.2f} % to {100 * high:.2f} % "
          f"(99.9 % binomial around 95.45 %), RMS of z {frame['z_rms_low'][0]:.3f} to {frame['z_rms_high'][0]:.3f} "
          f"(chi^2, 1 - 1e-5)\n")
    print("| parameter | within 2u | RMS of z | max abs z | passed |")
    print("|---|---|---|---|---|")
    for row in frame.iter_rows(named=True):
        print(f"| `{row['parameter']}` | {100 * row['fraction']:.2f} % | {row['z_rms']:.3f} | {row['max_abs_z']:.2f} | "
              f"{'yes' if row['passed'] else 'NO'} |")
    return 0 if frame["passed"].all() else 1


if __name__ == "__main__":
    sys.exit(main())
