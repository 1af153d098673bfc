"""Regenerate issue 15 item 2's figures: the diagnosis of simulated static
hand-pose sessions (``tests/handsim.py``: 30 poses of random orientation,
4 s rests joined by 3 s turns at 100 Hz, the default DUT of 8 counts
noise), each run through ``rotcal run``.

    nice python scripts/static_diagnosis_acceptance.py [--seeds 10] [--clean 20] [--workers 2] [--excess 0] [--noise SHAPE]

Cases: each of cubic_nonlinearity, quadratic_nonlinearity, offset_drift and
thermal at the size of ``SIZES`` (a random channel and sign; thermal with
the catalogue's random sensitivity coefficient and warm-up), 10 seeds each,
and 20 clean sessions. Counts, per case: the effect named on its channel,
sessions with any other finding, and the named parameters within 3u of the
truth. ``--excess S``: every rest's mean off by a normal S counts per
channel (an unsteady hand; the tests are then F tests). ``--noise SHAPE``:
the noise of ``scripts/noise_coverage.py``'s shape (its white part 6 counts)
drawn over the whole session in place of the DUT's white noise. Prints a
Markdown table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from noise_coverage import SHAPES, noise_request  # noqa: E402

from rotcal.model.effects import effect_named  # noqa: E402
from rotcal.run import run_dataset  # noqa: E402
from rotcal.simulate import SimulationSpec  # noqa: E402
from rotcal.simulate.core import dut_noise  # noqa: E402

from handsim import hand_session, write_session  # noqa: E402

# sizes within the catalogue's ranges (docs/effects.md), above the 80 %-power sizes of these sessions
SIZES = {"cubic_nonlinearity": 8e-4, "quadratic_nonlinearity": 6e-4, "offset_drift": 0.025, "thermal": 1.5}


def request(name: str, seed: int) -> tuple[str, str]:
    rng = np.random.default_rng(5000 + seed)
    channel = str(rng.choice(("u", "v", "w")))
    return effect_named(name).draw(SIZES[name], float(rng.choice([-1.0, 1.0])), "x", channel, rng), channel


def one(case: str, seed: int, excess: float, shape: str = "white") -> dict:
    effects, channel = ((), "") if case == "clean" else (lambda r: ((r[0],), r[1]))(request(case, seed))
    wanted = noise_request(shape, seed) if shape != "white" else ""
    noise = dut_noise(SimulationSpec().with_noise(wanted)) if wanted else None
    frame, truth = hand_session(seed, effects, excess=excess, noise=noise)
    with tempfile.TemporaryDirectory() as tmp:
        outcome = run_dataset(write_session(Path(tmp) / "data", frame), Path(tmp) / "out")
    findings = outcome.diagnosis.findings.filter("detected")
    named = findings.filter((findings["effect"] == case) & findings["where"].str.starts_with(f"channel {channel}"))
    params = outcome.diagnosis.parameters.filter(outcome.diagnosis.parameters["effect"] == case)
    within = [abs(v - truth.get(p, 0.0)) <= 3 * u for p, v, u in params.select("parameter", "value", "std_uncertainty").iter_rows()]
    return {"case": case, "named": named.height == 1, "other": findings.height - named.height > 0,
            "within": sum(within), "params": len(within)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--clean", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--excess", type=float, default=0.0)
    parser.add_argument("--noise", default="white", choices=SHAPES)
    args = parser.parse_args()
    cases = SIZES if args.seeds else {}
    jobs = [(case, seed) for case in cases for seed in range(args.seeds)] + [("clean", 100 + s) for s in range(args.clean)]
    with ProcessPoolExecutor(args.workers) as pool:
        results = list(pool.map(one, *zip(*jobs), [args.excess] * len(jobs), [args.noise] * len(jobs)))
    print("| case | size | sessions | named on its channel | with another finding | parameters within 3u |")
    print("|---|---|---|---|---|---|")
    for case in (*cases, "clean"):
        rows = [r for r in results if r["case"] == case]
        size = f"{effect_named(case).size_of.split(',')[0].split(' (')[0]} = {SIZES[case]:g}" if case in SIZES else ""
        within, params = sum(r["within"] for r in rows), sum(r["params"] for r in rows)
        print(f"| {case} | {size} | {len(rows)} | {sum(r['named'] for r in rows)} | {sum(r['other'] for r in rows)} | "
              f"{within} of {params} |")


if __name__ == "__main__":
    main()
