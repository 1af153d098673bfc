"""Regenerate issue 13 item 3's figures: static steps faster than a sample
and dwells at low output rates, in recordings whose logger paused between
segments, found from ``t, u, v, w`` alone.

    python scripts/steps_acceptance.py [--seeds 10] [--first 1] [--workers 2]

Scenarios (``tests/steps_checks.py``, one recording per seed): the default
plan with step moves of zero time and the logger paused 5 s between
segments (the acceptance case); the default plan, whose logger also pauses
during the 1 s step moves; the continuous recording of issue 5 (slow moves,
the logger never paused); the acceptance case at 20, 5 and 2 Hz output (at
2 Hz six samples a step); and a continuous recording with instantaneous
steps.
Prints a Markdown table: seeds with every rate found (0 Hz included),
values beyond 3u of the truth, the normalised errors' RMS and largest,
static sequences and their steps, missing-sample warnings, pauses reported.
Then the same recordings with packets lost at random (three runs of 2 s
each): the lost runs inside a segment must stay gaps (missing samples), and
those between segments become pauses.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from steps_checks import LOST_PACKETS, SCENARIOS, StepsChecked, check_lost_packets, check_steps  # noqa: E402

RATES = (0.0, 0.01, 0.05, 0.1, 0.5)


def _one(args: tuple[str, int]) -> StepsChecked:
    scenario, seed = args
    with tempfile.TemporaryDirectory() as work:
        return check_steps(scenario, seed, Path(work))


def _lost(args: tuple[str, int]) -> tuple[str, tuple[int, int, int, int]]:
    scenario, seed = args
    with tempfile.TemporaryDirectory() as work:
        return scenario, check_lost_packets(scenario, seed, Path(work))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=1)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    jobs = [(scenario, args.first + s) for scenario in SCENARIOS for s in range(args.seeds)]
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(_one, jobs))
    print("| scenario (`--plan`) | seeds with every rate, 0 Hz included | values beyond 3u | RMS of z | largest abs(z) "
          "| static sequences (steps) | missing-sample warnings | pauses reported per seed |")
    print("|---|---|---|---|---|---|---|---|")
    for scenario, plan in SCENARIOS.items():
        rows = [r for r in results if r.scenario == scenario]
        every = sum(r.rates == RATES for r in rows)
        z = np.concatenate([v for r in rows for v in r.z.values()])
        beyond = sum(r.beyond() for r in rows)
        sequences = sorted({f"{len(r.sequences)} of {'/'.join(map(str, sorted(set(r.sequences))))} steps"
                            if r.sequences else "none" for r in rows})
        pauses = sorted({f"{r.pauses:g}" for r in rows})
        print(f"| {scenario} (`{plan}`) | {every}/{len(rows)} | {beyond}/{z.size} ({100 * beyond / max(z.size, 1):.2g} %) "
              f"| {np.sqrt(np.mean(z**2)):.2f} | {np.abs(z).max():.2f} | {', '.join(sequences)} "
              f"| {sum(len(r.missing_warnings) for r in rows)} | {', '.join(pauses)} |")
    lossy = [s for s, plan in SCENARIOS.items() if "dt_s=0.5" not in plan]
    with ProcessPoolExecutor(args.workers) as pool:
        lost = list(pool.map(_lost, [(scenario, args.first + s) for scenario in lossy for s in range(args.seeds)]))
    print(f"\n| scenario, `--timebase {LOST_PACKETS}` | lost runs inside segments: reported as gaps "
          "| lost runs between segments: reported as pauses |")
    print("|---|---|---|")
    for scenario in lossy:
        inside, between, gaps, pauses = np.sum([r for s, r in lost if s == scenario], axis=0)
        print(f"| {scenario} | {gaps} of {inside} | {pauses} of {between} |")


if __name__ == "__main__":
    main()
