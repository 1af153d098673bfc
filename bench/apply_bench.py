"""``rotcal apply``'s correction, samples per second on one core:
``apply.correct`` (a = P (R - O)) and ``apply.correction_covariance`` (each
sample's covariance, --uncertainty) against a plain numpy matrix product
``P @ R`` of the same arrays, the floor of any correction.

    python bench/apply_bench.py [--samples 10000000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
from common import best_of, report  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from rotcal.apply import correct, correction_covariance  # noqa: E402
from rotcal.model.calibration import rate_calibration  # noqa: E402
from rotcal.model.results import BudgetInput, IntrinsicResult  # noqa: E402

G = 9.80665


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=10_000_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    rng = np.random.default_rng(1)
    state = np.concatenate([(np.eye(3) * 170 + rng.normal(0, 2, (3, 3))).ravel() * G, [-240.0, 17.0, 226.0]])
    half = rng.normal(0, 1e-2, (12, 12))
    cov = half @ half.T
    result = IntrinsicResult.from_state(0.0, state, cov, G, 1e-5, [(BudgetInput("seg1", "segment", 1, "x", 30), cov)])
    rc = rate_calibration(result, "table", "baseline", "benchmark", "bit")
    raw = rng.integers(-32768, 32768, (3, args.samples)).astype(np.float64)
    P, O = rc.P_matrix, rc.O_vector  # noqa: E741
    n = args.samples
    with threadpool_limits(limits=1):
        floor = best_of(lambda: P @ raw, args.repeats)
        report(f"apply correction ({n:,} samples, one core)", n, "samples", best_of(lambda: correct(raw, P, O), args.repeats),
               "numpy P @ R", floor)
        report(f"apply --uncertainty covariance ({n:,} samples, one core)", n, "samples",
               best_of(lambda: correction_covariance(raw, rc), max(1, args.repeats // 2)), "numpy P @ R", floor)


if __name__ == "__main__":
    main()
