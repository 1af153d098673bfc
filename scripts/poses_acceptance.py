"""Regenerate issue 13 item 4's figures: the nested static models on
simulated hand poses (``tests/posesim.py``).

    python scripts/poses_acceptance.py [--seeds 100] [--first 0] [--mode unknown|references|both]

Cases of unknown orientation (``--mode unknown``; one session per seed):

- ``hand poses, orthogonal``: ten poses (the six faces, two between v and
  w, two between w and u, none between u and v), each tilted by a normal
  3 degrees about a random axis; the DUT's axes orthogonal. Counts: the
  orthogonal model chosen; its sensitivities and offsets beyond 3u of the
  truth; the nine-parameter phi_uv within 2u of the truth (a session whose
  poses do not determine the nine counts as not within); the advice naming
  the u-v pose.
- ``random poses, phi_uv = 90.5``: 16 poses of random orientation; counts
  the nine-parameter model chosen.

Cases with known references (``--mode references``; ``refmodels``; the
DUT turned by a random 2-degree mount rotation against the references'
frame):

- ``labelled hand poses, orthogonal``: the ten poses above, each tilted by
  3 degrees, with their nominal directions as references (labels); counts
  as above, and the median u(phi_uv) of the 12-parameter fit beside that
  of the same session with two poses between u and v added, and with two
  faces (+u, +v) added instead: with known references a u-v pose is worth
  no more than a face, so no advice is due (``refmodels.reference_advice``).
- ``jig, random poses, phi_uv = 90.5``: 16 poses of random orientation with
  exact references; counts the 12-parameter model chosen.

Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from rotcal.combine.multiposition import pose_arrays  # noqa: E402
from rotcal.combine.posemodels import advice, choose_model  # noqa: E402
from rotcal.combine.poses import correct_poses  # noqa: E402
from rotcal.combine.refmodels import choose_reference_model  # noqa: E402
from rotcal.fit.means import pose_table  # noqa: E402
from rotcal.model.physics import rotation_matrix  # noqa: E402
from rotcal.model.results import Failure  # noqa: E402

from posesim import G_LOCAL, HAND_POSES, hand_placed, pose_bounds, random_directions, reference_pose_table, tilted  # noqa: E402

SIX = [0, 1, 2, 6, 7, 8]


def hand_case(seeds: range) -> dict[str, str]:
    chosen = beyond = within = determined = named = 0
    for seed in seeds:
        sim = hand_placed(seed, directions=tilted(HAND_POSES, seed), angles_deg=(90.0, 90.0, 90.0))
        poses = pose_table(sim.t_ns, sim.y, *pose_bounds(sim))
        choice = choose_model(poses, G_LOCAL, 0.0)
        assert not isinstance(choice.orthogonal, Failure), choice.orthogonal
        six = choice.orthogonal.result
        chosen += choice.chosen == "orthogonal"
        beyond += int(np.sum(np.abs(six.value - sim.truth)[SIX] > 3 * six.std_uncertainty[SIX]))
        general = choice.orthogonal if isinstance(choice.full, Failure) else choice.full
        if not isinstance(choice.full, Failure):
            determined += 1
            full = choice.full.result
            within += abs(full.value[3] - sim.truth[3]) <= 2 * full.std_uncertainty[3]
        directions = correct_poses(general.result, *pose_arrays(poses)).acceleration
        named += any("a pose between +u and +v" in a for a in advice(directions))
    n = len(seeds)
    return {"case": "hand poses, orthogonal", "sessions": str(n), "model chosen": f"orthogonal in {chosen}",
            "s, O beyond 3u": f"{beyond} of {6 * n} ({100 * beyond / (6 * n):.2f} %)",
            "full phi_uv within 2u": f"{within} of {n} ({determined} determined)", "advice names u-v pose": str(named)}


def non_orthogonal_case(seeds: range) -> dict[str, str]:
    chosen = 0
    p = []
    for seed in seeds:
        sim = hand_placed(seed, n_poses=16, angles_deg=(90.5, 90.0, 90.0))
        choice = choose_model(pose_table(sim.t_ns, sim.y, *pose_bounds(sim)), G_LOCAL, 0.0)
        chosen += choice.chosen == "baseline"
        p.append(choice.p_value)
    return {"case": "random poses, phi_uv = 90.5", "sessions": str(len(seeds)), "model chosen": f"nine in {chosen}",
            "s, O beyond 3u": "", "full phi_uv within 2u": "", "advice names u-v pose": f"largest p {max(p):.2g}"}


def mount(seed: int) -> np.ndarray:
    """The DUT's rotation against the references' frame: 2 degrees about a random axis."""
    return rotation_matrix(np.random.default_rng(20_000 + seed).standard_normal(3), 2.0)


def reference_hand_case(seeds: range) -> dict[str, str]:
    chosen = beyond = within = 0
    r = np.sqrt(0.5)
    extra = {"": np.zeros((0, 3)), "two u-v poses": np.array([[r, r, 0.0], [-r, r, 0.0]]),
             "two faces (+u, +v)": np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])}
    u_phi: dict[str, list[float]] = {name: [] for name in extra}
    for seed in seeds:
        for name, added in extra.items():
            references = np.vstack([HAND_POSES, added])
            sim = hand_placed(seed, directions=tilted(references @ mount(seed).T, seed), angles_deg=(90.0, 90.0, 90.0))
            choice = choose_reference_model(reference_pose_table(sim, references), G_LOCAL, 0.0)
            assert not isinstance(choice, Failure) and not isinstance(choice.full, Failure), choice
            full = choice.full.result
            u_phi[name].append(full.std_uncertainty[3])
            if name:
                continue
            assert not isinstance(choice.orthogonal, Failure), choice.orthogonal
            six = choice.orthogonal.result
            chosen += choice.chosen == "orthogonal"
            beyond += int(np.sum(np.abs(six.value - sim.truth)[SIX] > 3 * six.std_uncertainty[SIX]))
            within += abs(full.value[3] - sim.truth[3]) <= 2 * full.std_uncertainty[3]
    n = len(seeds)
    medians = ", ".join(f"{np.median(u):.3f} with {name} added" for name, u in u_phi.items() if name)
    return {"case": "labelled hand poses, orthogonal (known references)", "sessions": str(n),
            "model chosen": f"orthogonal in {chosen}", "s, O beyond 3u": f"{beyond} of {6 * n} ({100 * beyond / (6 * n):.2f} %)",
            "full phi_uv within 2u": f"{within} of {n}",
            "advice names u-v pose": f"none due (references span 3-D); median u(phi_uv) {np.median(u_phi['']):.3f} deg, {medians}"}


def reference_non_orthogonal_case(seeds: range) -> dict[str, str]:
    chosen = 0
    p = []
    for seed in seeds:
        references = random_directions(np.random.default_rng(30_000 + seed), 16)
        sim = hand_placed(seed, directions=references @ mount(seed).T, angles_deg=(90.5, 90.0, 90.0))
        choice = choose_reference_model(reference_pose_table(sim, references), G_LOCAL, 0.0)
        assert not isinstance(choice, Failure)
        chosen += choice.chosen == "baseline"
        p.append(choice.p_value)
    return {"case": "jig, random poses, phi_uv = 90.5 (known references)", "sessions": str(len(seeds)),
            "model chosen": f"twelve in {chosen}", "s, O beyond 3u": "", "full phi_uv within 2u": "",
            "advice names u-v pose": f"largest p {max(p):.2g}"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--mode", choices=("unknown", "references", "both"), default="both")
    args = parser.parse_args()
    seeds = range(args.first, args.first + args.seeds)
    rows = ([hand_case(seeds), non_orthogonal_case(seeds)] if args.mode != "references" else []) + \
        ([reference_hand_case(seeds), reference_non_orthogonal_case(seeds)] if args.mode != "unknown" else [])
    print("| " + " | ".join(rows[0]) + " |")
    print("|" + "---|" * len(rows[0]))
    for row in rows:
        print("| " + " | ".join(row.values()) + " |")


if __name__ == "__main__":
    main()
