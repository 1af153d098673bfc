"""The fit stage, samples per second: ``fit.fit_segments`` (every static and
rotation segment, all three channels, covariances and residual statistics)
against ``scipy.optimize.curve_fit`` of C + A sin(theta) + B cos(theta)
applied to each segment and channel (the call as written by hand, default
starting values; given good ones it needs 9 instead of 33 evaluations), and against one ``numpy.sum`` pass over
the same arrays (angle and three channels: the memory-bandwidth floor).

Two datasets: the default plan (15 segments, 54,000 samples) and the same
plan with longer rotations (``--rotation-samples``, default 100,000 per
segment, 1.2 million samples: arrays larger than the caches).

    python bench/fit_stage.py [--rotation-samples 100000] [--repeats 5]
"""

from __future__ import annotations

import argparse
import sys
from functools import partial
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402
import polars as pl  # noqa: E402
from common import best_of, report  # noqa: E402
from scipy.optimize import curve_fit  # noqa: E402
from threadpoolctl import threadpool_limits  # noqa: E402

from rotcal.config import FitConfig  # noqa: E402
from rotcal.fit.segments import fit_segments, segment_rows  # noqa: E402
from rotcal.ingest.labels import label_columns  # noqa: E402
from rotcal.segment.labelled import segment_by_labels  # noqa: E402
from rotcal.simulate import Plan, SimulationSpec, simulate  # noqa: E402
from rotcal.tables import conform  # noqa: E402


def stage_input(rotation_samples: int) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The fit stage's input tables (samples with segments, segments) of a simulated dataset."""
    sim = simulate(SimulationSpec(plan=Plan(rotation_samples=rotation_samples)), 1)
    frame = label_columns(sim.samples.drop("plan_segment"), None, Path("simulated"))
    return segment_by_labels(conform(frame, "samples"), "bench")


def sine(theta_rad, c, a, b):
    return c + a * np.sin(theta_rad) + b * np.cos(theta_rad)


def curve_fit_each(samples: pl.DataFrame, segments: pl.DataFrame) -> None:
    rows = segment_rows(samples)
    for seg in segments["segment"]:
        part = samples.slice(*rows[seg])
        theta = np.deg2rad(part["angle_deg"].to_numpy())
        for channel in ("u", "v", "w"):
            y = part[channel].to_numpy()
            curve_fit(sine, theta, y)  # as written by hand: default starting values


def _sums(arrays: list[np.ndarray]) -> list:
    """The floor: one pass over each column."""
    return [np.sum(a) for a in arrays]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotation-samples", type=int, default=100_000)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    for rotation_samples in (Plan().rotation_samples, args.rotation_samples):
        samples, segments = stage_input(rotation_samples)
        n = samples.height
        arrays = [samples[c].to_numpy() for c in ("angle_deg", "u", "v", "w")]
        with threadpool_limits(limits=1, user_api="blas"):  # as run_dataset does
            ours = best_of(partial(fit_segments, samples, segments, FitConfig()), args.repeats)
            floor = best_of(partial(_sums, arrays), args.repeats)
            reference = best_of(partial(curve_fit_each, samples, segments), max(1, args.repeats // 2))
        what = f"fit stage ({segments.height} segments, {n:,} samples)"
        report(what, n, "samples", ours, "curve_fit per segment and channel", reference)
        ratio = floor / ours
        print(f"{what}: {100 * ratio:.1f} % of one numpy.sum pass over angle, u, v, w ({n / floor:,.0f} samples/s)", flush=True)


if __name__ == "__main__":
    main()
