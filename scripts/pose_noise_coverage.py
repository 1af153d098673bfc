"""Static poses under coloured noise: for each noise shape of
``scripts/noise_coverage.py``, seeded sessions of hand-placed poses of
random orientation (``tests/posesim.py``: 24 poses of 30 s at 0.06 s
with 6 s turns between them, about 14 minutes; the noise drawn over the
whole session), and per shape the sd of the normalised errors
z = (estimate - truth) / u and the fraction |z| <= 2 of the pose means
(``fit.means.modelled_pose_table``, the stage on its own: the noise model
of the poses' residuals; then as the labelled fit weighs them, with the
wander their scatter shows, ``noise.poses``) and of the nine parameters
per class (s, phi, O) of the orientation-free model
(``combine.posemodels``, nine parameters) and of the labelled one
(``combine.refmodels``: each pose's true direction as its reference), both
by generalised least squares with the pose means' covariance.

    python scripts/pose_noise_coverage.py [--sessions 50] [--shapes white,gauss_markov,...]

Prints a Markdown table. About 0.7 s a session.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from noise_coverage import CLASSES, SHAPES, WHITE_SD, noise_request  # noqa: E402

from rotcal.combine.posemodels import choose_model  # noqa: E402
from rotcal.combine.refmodels import choose_reference_model  # noqa: E402
from rotcal.fit.means import modelled_pose_table  # noqa: E402
from rotcal.model.results import Failure  # noqa: E402
from rotcal.simulate import SimulationSpec  # noqa: E402
from rotcal.simulate.core import dut_noise  # noqa: E402
from rotcal.simulate.noise import NoiseSpec, draw_channels  # noqa: E402

from posesim import G_LOCAL, hand_placed, pose_bounds  # noqa: E402

DT_S = 0.06
POSE_SAMPLES = 500
MOVE_SAMPLES = 100


def session(shape: str, seed: int) -> dict[str, np.ndarray]:
    """One session's normalised errors: pose means (poses x channels), and
    the nine parameters of the orientation-free and labelled models."""
    request = noise_request(shape, seed)
    noise = dut_noise(SimulationSpec().with_noise(request)) if request else NoiseSpec(white_sd=WHITE_SD)
    clean = hand_placed(seed, samples=POSE_SAMPLES, noise=0.0, move_samples=MOVE_SAMPLES, dt_s=DT_S, integer=False)
    y = clean.y + draw_channels(noise, len(clean.y), 1 / DT_S, np.random.default_rng([seed, 0x505]), 3)
    starts, stops = pose_bounds(clean)
    poses, between = modelled_pose_table(clean.t_ns, y, starts, stops)
    truth_means = np.array([clean.y[a:b].mean(axis=0) for a, b in zip(starts, stops)])
    means = poses.select("mean_u", "mean_v", "mean_w").to_numpy()
    u = np.sqrt(np.array(poses["cov_mean"].to_list())[:, [0, 4, 8]])
    out = {"means": ((means - truth_means) / u).ravel()}
    free = choose_model(poses, G_LOCAL, 0.0, between=between).full
    if not isinstance(free, Failure):
        out["orientation-free"] = (free.result.value - clean.truth) / free.result.std_uncertainty
    labelled = choose_reference_model(poses.with_columns(ref_x=clean.directions[:, 0], ref_y=clean.directions[:, 1],
                                                         ref_z=clean.directions[:, 2]), G_LOCAL, 0.0, between=between)
    if not isinstance(labelled, Failure) and not isinstance(labelled.full, Failure):
        out["labelled"] = (labelled.full.result.value - clean.truth) / labelled.full.result.std_uncertainty
        if labelled.full.pose_cov is not None:  # the pose means as the labelled fit weighs them: with the wander
            u_weighed = np.sqrt(np.einsum("rkk->kr", labelled.full.pose_cov.channels))
            out["weighed means"] = ((means - truth_means) / u_weighed).ravel()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=50)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--shapes", default=",".join(SHAPES))
    args = parser.parse_args()
    start = time.perf_counter()
    print("| shape | sessions | pose means: stage, weighed | orientation-free: s, phi, O | labelled: s, phi, O |")
    print("|---|---|---|---|---|")
    for shape in args.shapes.split(","):
        rows = [session(shape, args.first_seed + k) for k in range(args.sessions)]

        def cell(z: np.ndarray) -> str:
            return f"{np.sqrt(np.mean(z**2)):.2f} ({100 * np.mean(np.abs(z) <= 2):.0f} %)"

        weighed = [r["weighed means"] for r in rows if "weighed means" in r]
        cells = [cell(np.concatenate([r["means"] for r in rows])) + ", " + (cell(np.concatenate(weighed)) if weighed else "-")]
        for model in ("orientation-free", "labelled"):
            z = np.array([r[model] for r in rows if model in r])
            cells.append(", ".join(cell(z[:, list(idx)]) for idx in CLASSES.values()) if z.size else "-")
        print(f"| {shape} | {len(rows)} | " + " | ".join(cells) + " |", flush=True)
    print(f"\n{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
