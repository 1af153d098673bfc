"""Whether a richer static model is recommended only when it predicts
held-out poses better (``combine.heldout``): simulated hand-pose sessions
(``tests/handsim.py``: rests of 4 s at 100 Hz, 8 counts noise, so a rest's
mean has 0.4 counts of noise), every rest's mean off by a normal
``--excess`` counts per channel (default 1.2: between-pose scatter three
times the within-pose noise), each run through ``rotcal run``.

    nice python scripts/heldout_acceptance.py [--seeds 100] [--first 0] [--k3 0] [--poses 0]

``--poses 0``: each session 10 to 40 poses (drawn per seed); ``--k3 S``: a
cubic nonlinearity of size S on a random channel and sign. Counts the
sessions whose recommended model is the refined one (an effect modelled)
and prints one Markdown row.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from rotcal.model.effects import effect_named  # noqa: E402
from rotcal.run import run_dataset  # noqa: E402

from handsim import hand_session, write_session  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--first", type=int, default=0)
    parser.add_argument("--k3", type=float, default=0.0)
    parser.add_argument("--poses", type=int, default=0)
    parser.add_argument("--excess", type=float, default=1.2)
    args = parser.parse_args()
    refined = 0
    for seed in range(args.first, args.first + args.seeds):
        rng = np.random.default_rng(900 + seed)
        n = args.poses or int(rng.integers(10, 41))
        effects = ()
        if args.k3:
            channel = str(rng.choice(("u", "v", "w")))
            effects = (effect_named("cubic_nonlinearity").draw(args.k3, float(rng.choice([-1.0, 1.0])), "x", channel, rng),)
        frame, _ = hand_session(seed, effects, n_poses=n, excess=args.excess)
        with tempfile.TemporaryDirectory() as tmp:
            outcome = run_dataset(write_session(Path(tmp) / "data", frame), Path(tmp) / "out")
        refined += outcome.recommended.model == "refined"
    poses = args.poses or "10-40"
    print(f"| {poses} | {args.excess:g} | {args.k3:g} | {args.seeds} | {refined} |")


if __name__ == "__main__":
    main()
