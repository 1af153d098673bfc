"""The six-face test by hand (``tests/sixfaces.py``): per seed a DUT with
gains within 2 %, offsets up to 5 % of full scale, its axes within
``--misalignment`` degrees of orthogonal and turned in its case by up to
1 degree; six faces each tilted by up to 3 degrees; reduced labelled and
unlabelled (``combine.static.reduce_static``, the run's static reduction).

    python scripts/six_faces_acceptance.py [--seeds 100] [--misalignment 1.0]

Counts, of the seeds: reduced (a result, not a refusal); offsets and
sensitivities at least as close to the truth as (up + down) / 2 (RMS over
the three axes); each of s_u, s_v, s_w, O_u, O_v, O_w within 2u of the
truth; and, with the third face placed 6 degrees off, that face named.
Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from sixfaces import G_LOCAL, closeness, pose_tables, six_faces  # noqa: E402

from rotcal.combine.static import reduce_static  # noqa: E402
from rotcal.model.placement import Placement  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--misalignment", type=float, default=1.0)
    parser.add_argument("--first", type=int, default=0)
    args = parser.parse_args()
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


if __name__ == "__main__":
    main()
