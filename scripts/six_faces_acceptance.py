"""The six-face test by hand (``tests/sixfaces.py``): per seed a DUT with
gains within 2 %, offsets up to 5 % of full scale, its axes within
``--misalignment`` degrees of orthogonal and turned in its case by up to
1 degree; six faces each tilted by up to 3 degrees; reduced labelled and
unlabelled (``combine.static.reduce_static``, the run's static reduction).

    python scripts/six_faces_acceptance.py [--seeds 100] [--misalignment 1.0] [--bound]

Counts, of the seeds: reduced (a result, not a refusal); offsets and
sensitivities at least as close to the truth as (up + down) / 2 (RMS over
the three axes); each of s_u, s_v, s_w, O_u, O_v, O_w within 2u of the
truth; and, with the third face placed 6 degrees off, that face named.
Prints a Markdown table. ``--bound``: instead, what other estimators of
the same six pose means achieve (labelled), beside the fit: the oracle (the
true angles), the posterior means of the angles' share of the faces' cross
readings (Gaussian priors; the simulator's own priors) and blends of the
fit's offsets with (up + down) / 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sixfaces import FACES, G_LOCAL, closeness, pose_tables, six_faces  # noqa: E402

from rotcal.combine.multiposition import ORTHOGONAL, TRIL, _solve, pose_arrays  # noqa: E402
from rotcal.combine.static import reduce_static  # noqa: E402
from rotcal.model.physics import rotation_matrix, unit_vectors_from_angles  # noqa: E402
from rotcal.model.placement import Placement  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--misalignment", type=float, default=1.0)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--bound", action="store_true", help="other estimators of the same pose means (slower)")
    args = parser.parse_args()
    if args.bound:
        bound(args.first, args.seeds, args.misalignment)
        return
    print("| poses | reduced | offsets at least as close as (up+down)/2 | sensitivities too | "
          "within 2u (s_u s_v s_w O_u O_v O_w) | 6-degree face named |")
    print("|---|---|---|---|---|---|")
    for which in (0, 1):
        reduced, counts, named = 0, {"offsets": 0, "sensitivities": 0, "within_2u": np.zeros(6, int)}, 0
        for seed in range(args.first, args.first + args.seeds):
            session = six_faces(seed, misalignment_deg=args.misalignment)
            reduction = reduce_static(None, None, "six", G_LOCAL, 0.0, pose_tables(session)[which], Placement())
            if not reduction.results:
                continue
            reduced += 1
            r = reduction.result
            for key, hit in closeness(session, r.value, r.std_uncertainty).items():
                counts[key] = counts[key] + hit.astype(int)
            off = six_faces(seed, misalignment_deg=args.misalignment, off_label={2: 6.0})
            named += which == 0 and any(w.startswith("pose 2 (y_p) rests") for w in
                                        reduce_static(None, None, "six", G_LOCAL, 0.0, pose_tables(off)[0], Placement()).warnings)
        print(f"| {'labelled' if which == 0 else 'unlabelled'} | {reduced} | {counts['offsets']} | {counts['sensitivities']} | "
              f"{' '.join(map(str, counts['within_2u']))} | {named if which == 0 else '-'} |")


# --bound: what estimators of the same six pose means achieve (docs/measured.md, "Decisions on hand-made recordings").
# Per seed, from the orthogonal fit's parameters p (L's diagonal and O) and the pose means: the fit itself; the
# oracle (the true angles, hence the true tilts: noise alone); the posterior mean of the angles under Gaussian
# priors (cos phi_ij = delta_ij + delta_ji, each axis's deviation from its face's normal; S_ij, the half-differences
# of the cross readings on i's and j's faces summed, = cos phi_ij + tilts of variance sigma_t^2: E[cos | S] =
# k S, k = sigma_m^2 / (sigma_m^2 + sigma_t^2)); the same under the simulator's own priors (uniform angles within
# 1 degree, its case rotation, tilts uniform in magnitude within 3 degrees), by importance sampling; and the
# offsets' blend O_ud + lam (O_fit - O_ud) of the fit with (up + down) / 2.
DEG = np.pi / 180
SIGMA_M2 = (1.0 * DEG) ** 2 / 3  # cos phi: rectangular within 1 degree (the simulator's bound)
SIGMA_T2 = (3.0 * DEG) ** 2 / 6  # a face's tilt, per component: magnitude uniform within 3 degrees, any direction


def _lower(p: np.ndarray) -> np.ndarray:
    L = np.zeros((3, 3))
    L[TRIL] = p[:6]
    return L


def _with_angles(p: np.ndarray, m: np.ndarray, cos: np.ndarray) -> np.ndarray:
    """The six-face fit with the angles' cosines (uv, vw, wu) fixed at ``cos`` instead of 0."""
    for _ in range(3):
        s = np.linalg.norm(_lower(p), axis=1)
        unit = unit_vectors_from_angles(*np.degrees(np.arccos(cos)))
        p = _solve(np.concatenate([(s[:, None] * unit)[TRIL], p[6:]]), m, G_LOCAL, np.ones(len(m)), ORTHOGONAL)
    return p


def _s_statistic(p: np.ndarray, m: np.ndarray) -> np.ndarray:
    """S_uv, S_vw, S_wu of the fit's corrected directions."""
    a = np.linalg.solve(_lower(p), (m - p[6:]).T).T
    d = a / np.linalg.norm(a, axis=1)[:, None]
    up, down = d.argmax(axis=0), d.argmin(axis=0)
    half = lambda i, j: (d[up[i], j] - d[down[i], j]) / 2  # noqa: E731
    return np.array([half(i, j) + half(j, i) for i, j in ((0, 1), (1, 2), (2, 0))])


def _exact_prior(p: np.ndarray, m: np.ndarray, rng: np.random.Generator, n: int = 40000) -> np.ndarray:
    """The posterior mean of the six under the simulator's priors: angles and case rotation drawn from them, the
    fit (quadratic in the cosines, from 19 fits) and the faces' tilts from their labels (weight prod 1/theta within
    3 degrees, the density of a tilt uniform in magnitude)."""
    eps = DEG
    design = np.array([np.zeros(3)] + [sign * eps * np.eye(3)[i] for i in range(3) for sign in (1, -1)]
                      + [eps * (si * np.eye(3)[i] + sj * np.eye(3)[j]) for i in range(3) for j in range(i + 1, 3)
                         for si in (1, -1) for sj in (1, -1)])
    features = lambda x: np.column_stack([np.ones(len(x)), x, x**2, x[:, [0]] * x[:, [1]], x[:, [1]] * x[:, [2]],  # noqa: E731
                                          x[:, [0]] * x[:, [2]]])
    coef = np.linalg.lstsq(features(design), np.array([_with_angles(p, m, c) for c in design]), rcond=None)[0]
    draws = features(np.cos(np.deg2rad(90 + rng.uniform(-1, 1, (n, 3))))) @ coef
    L = np.zeros((n, 3, 3))
    L[:, TRIL[0], TRIL[1]] = draws[:, :6]
    a = np.linalg.solve(L[:, None], (m[None] - draws[:, None, 6:])[..., None])[..., 0]
    rotation = np.array([rotation_matrix(axis, angle) for axis, angle in zip(rng.standard_normal((n, 3)), rng.uniform(0, 1, n))])
    d = np.einsum("nji,nkj->nki", rotation, a / np.linalg.norm(a, axis=2)[..., None])  # in the case's frame
    tilt = np.degrees(np.arccos(np.clip(np.einsum("nki,ki->nk", d, FACES), -1, 1)))
    weight = np.where(np.all(tilt <= 3.0, axis=1), np.prod(1 / np.maximum(tilt, 1e-3), axis=1), 0.0)
    return weight @ draws / weight.sum()


def bound(first: int, seeds: int, misalignment: float) -> None:
    """One table row per estimator: offsets and sensitivities at least as close as (up + down) / 2, and their RMS
    errors over the seeds (counts; ppm)."""
    k = SIGMA_M2 / (SIGMA_M2 + SIGMA_T2)
    names = ("(up+down)/2", "orthogonal fit (today)", "oracle: true angles", f"posterior mean, Gaussian priors (k = {k:.2f})",
             "posterior mean, the simulator's priors (angles within 1 degree)",
             "blend lam 0.82 (Gaussian priors' weight)", "blend lam 0.3")
    wins, errors = np.zeros((len(names), 2), int), [[] for _ in names]
    rng = np.random.default_rng(0)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    for seed in range(first, first + seeds):
        session = six_faces(seed, misalignment_deg=misalignment)
        fit = reduce_static(None, None, "six", G_LOCAL, 0.0, pose_tables(session)[0], Placement()).fit
        p = np.concatenate([(fit.result.state[:9].reshape(3, 3) / G_LOCAL)[TRIL], fit.result.state[9:]])
        m = pose_arrays(pose_tables(session)[0])[0]
        s_ud, o_ud = session.up_down()
        truth = session.truth
        ud = np.concatenate([(s_ud[:, None] * np.eye(3))[TRIL], o_ud])
        estimates = [ud, p, _with_angles(p, m, np.cos(np.deg2rad(truth[3:6]))), _with_angles(p, m, k * _s_statistic(p, m)),
                     _exact_prior(p, m, rng), p, p]
        for row, (name, e) in enumerate(zip(names, estimates)):
            s, o = np.linalg.norm(_lower(e), axis=1), e[6:]
            if name.startswith("blend"):
                o = o_ud + float(name.split()[2]) * (o - o_ud)
            eo, es = o - truth[6:], s / truth[:3] - 1
            wins[row] += [rms(eo) <= rms(o_ud - truth[6:]), rms(es) <= rms(s_ud / truth[:3] - 1)]
            errors[row].append((rms(eo), rms(es)))
    print(f"| estimator (seeds {first}-{first + seeds - 1}, misalignment {misalignment:g}) | offsets at least as close "
          "as (up+down)/2 | sensitivities too | RMS offset error (counts) | RMS sensitivity error (ppm) |")
    print("|---|---|---|---|---|")
    for name, (wo, ws), err in zip(names, wins, errors):
        e = np.array(err)
        print(f"| {name} | {wo} | {ws} | {rms(e[:, 0]):.2f} | {1e6 * rms(e[:, 1]):.0f} |")


if __name__ == "__main__":
    main()
