"""The best power any test of a static effect can have on the hand sessions
of ``static_diagnosis_acceptance.py`` (``tests/handsim.py``: 30 poses of
random orientation, 4 s rests joined by 3 s turns at 100 Hz, orientation
free) under a noise shape: the likelihood-ratio test that knows the pose
means' true covariance and the effect's channel, at the diagnosis's false
alarm rate ([diagnosis] false_alarm, 1e-4).

Each pose's |a| scalar f_k = |A (m_k - O)| (A = the responsivity's
inverse, lower triangular: the orientation-free model's nine parameters)
moves by h_k . dm_k for an effect's change dm_k of the pose mean (h_k =
df / dm, the noise's projection too). With Sigma the scalars' covariance
(``noise.means.window_mean_covariance`` of the shape's terms over the
poses' windows, projected by h), the generalised least-squares statistic
is noncentral chi-square with one degree of freedom and noncentrality
lambda = d' W d - d' W J (J' W J)^-1 J' W d (W = Sigma^-1, J the nine
parameters' Jacobian); the power is its tail beyond the level's critical
value (Lehmann & Romano, Sec. 7.6).

    python scripts/static_power_bound.py [--seeds 10] [--scale 1.0]

``--scale``: the sizes of ``static_diagnosis_acceptance.SIZES`` times it.
Prints a Markdown table: per shape and effect, the median lambda and the
mean power over the seeds (the seeds, channels and signs of
``static_diagnosis_acceptance.request``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2, ncx2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from static_diagnosis_acceptance import SIZES, request  # noqa: E402

from rotcal.noise.means import NoiseProcess, window_mean_covariance  # noqa: E402

from handsim import session_draws  # noqa: E402
from posesim import G_LOCAL  # noqa: E402

DT_S, REST_S, MOVE_S, POSES = 0.01, 4.0, 3.0, 30
FALSE_ALARM = 1e-4
# the shapes' terms as processes (counts, s): white 8 (the DUT's); the mix of noise_coverage.py (white 6
# at 0.01 s, an AR(1) of 0.5 and sd 4 as a Gauss-Markov term of T = dt / ln 2, Gauss-Markov 300 s of sd 2,
# flicker B = 1, random walk K = 0.02; its low-pass at 0.4 of the rate keeps the density at 0 Hz)
SHAPES = {"white": NoiseProcess(8.0 * np.sqrt(DT_S)),
          "mix": NoiseProcess(6.0 * np.sqrt(DT_S), ((DT_S / np.log(2), 4.0), (300.0, 2.0)), 1.0, 0.02)}
EFFECTS = ("cubic_nonlinearity", "quadratic_nonlinearity", "offset_drift")


def noncentrality(seed: int, effect: str, size: float, cov: np.ndarray, t_mid: np.ndarray) -> float:
    """lambda of one session's effect (module docstring)."""
    dut, directions, *_ = session_draws(seed, POSES)
    y = G_LOCAL * directions @ dut.responsivity.T
    x1g = np.linalg.norm(dut.responsivity, axis=1) * G_LOCAL
    a_inv = np.linalg.inv(dut.responsivity)
    unit = y @ a_inv.T
    unit /= np.linalg.norm(unit, axis=1)[:, None]
    h = unit @ a_inv
    rows, cols = np.tril_indices(3)
    jac = np.column_stack([unit[:, rows] * y[:, cols], -h])
    weight = np.linalg.inv(np.einsum("kr,lr,kl->kl", h, h, cov))
    c = "uvw".index(request(effect, seed)[1])
    dm = np.zeros((POSES, 3))
    dm[:, c] = {"cubic_nonlinearity": y[:, c] * size * (y[:, c] / x1g[c]) ** 2,
                "quadratic_nonlinearity": y[:, c] * size * (y[:, c] / x1g[c]),
                "offset_drift": size * t_mid}[effect]
    d = np.einsum("kr,kr->k", h, dm)
    jw = jac.T @ weight
    return float(d @ weight @ d - (jw @ d) @ np.linalg.solve(jw @ jac, jw @ d))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--scale", type=float, default=1.0)
    args = parser.parse_args()
    start = np.arange(POSES) * (REST_S + MOVE_S)
    stop = start + REST_S
    critical = chi2.isf(FALSE_ALARM, 1)
    print("| shape | effect | size | median lambda | best power |")
    print("|---|---|---|---|---|")
    for shape, process in SHAPES.items():
        cov = window_mean_covariance(process, start, stop, DT_S, (0.0, float(stop[-1])))
        for effect in EFFECTS:
            size = SIZES[effect] * args.scale
            lam = np.array([noncentrality(s, effect, size, cov, (start + stop) / 2) for s in range(args.seeds)])
            print(f"| {shape} | {effect} | {size:g} | {np.median(lam):.1f} | {np.mean(ncx2.sf(critical, 1, lam)):.2f} |")


if __name__ == "__main__":
    main()
