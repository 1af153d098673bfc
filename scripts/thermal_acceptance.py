"""Regenerate issue 15 item 3's figures: the ``thermal`` effect on table
recordings of the default plan, against ``offset_drift`` and clean data.

    python scripts/thermal_acceptance.py [--seeds 10] [--first 10] [--workers 2]

Cases (one dataset per seed, seeds first .. first + seeds - 1):

- ``warm-up``: tco_v = 1.5 bit/K, tcs_v = 60 ppm/K, a 6 K exponential
  warm-up with a time constant of 25 % of the session;
- ``drawn warm-up``: the same coefficients, warm-up drawn from 3 to 8 K and
  its time constant from 10 to 40 % of the session;
- ``warm-up and step``: 3 K warm-up (20 %), then a -2 K step (air
  conditioning) at a drawn time;
- ``drift, constant T``: offset_drift drift_w = 0.02 bit/s, temperature_c
  logged at a constant 23 degree C;
- ``drift, logged warm-up``: the same drift while the logged temperature
  warms up 6 K (the DUT insensitive to it);
- ``clean, logged warm-up``: no effect, the temperature warming up 6 K.

Prints a Markdown table: how often each case is named exactly as the truth,
and the tco_v normalised errors where thermal is the truth.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import RunConfig, RunSection
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset

CASES = {
    "warm-up": (("thermal:tco_v=1.5,tcs_v=6e-5,warmup_k=6,tau_frac=0.25",), {"thermal"}),
    "drawn warm-up": (("thermal:tco_v=1.5,tcs_v=6e-5",), {"thermal"}),
    "warm-up and step": (("thermal:tco_v=1.5,tcs_v=6e-5,warmup_k=3,tau_frac=0.2,step_k=-2",), {"thermal"}),
    "drift, constant T": (("offset_drift:drift_w=0.02",), {"offset_drift"}),
    "drift, logged warm-up": (("offset_drift:drift_w=0.02", "thermal:tco_w=0,warmup_k=6,tau_frac=0.25"), {"offset_drift"}),
    "clean, logged warm-up": (("thermal:tco_w=0,warmup_k=6,tau_frac=0.25",), set()),
}


def case(args: tuple) -> tuple[str, int, list[str], float | None]:
    """One dataset: (case, seed, effects named, tco_v's normalised error or None)."""
    label, seed, workdir = args
    requests, _ = CASES[label]
    spec = SimulationSpec().with_effects(*requests)
    sim = simulate(spec, seed)
    if label == "drift, constant T":
        sim = dataclasses.replace(sim, samples=sim.samples.with_columns(temperature_c=pl.lit(23.0)))
    data = Path(workdir) / f"{label.replace(' ', '_').replace(',', '')}_{seed}"
    write_dataset(sim, spec, data / "data")
    run_dataset(data / "data", data / "out", config=RunConfig(run=RunSection(workers=1)))
    named = sorted(set(pl.read_parquet(data / "out" / "diagnosis.parquet").filter(pl.col("detected"))["effect"]))
    params = pl.read_parquet(data / "out" / "effect_parameters.parquet").filter(pl.col("parameter") == "tco_v")
    z = None
    if params.height and "thermal" in CASES[label][1]:
        z = float((params["value"].item() - 1.5) / params["std_uncertainty"].item())
    return label, seed, named, z


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first", type=int, default=10)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as workdir, ProcessPoolExecutor(args.workers) as pool:
        jobs = [(label, args.first + s, workdir) for label in CASES for s in range(args.seeds)]
        results = list(pool.map(case, jobs))
    print("| case | seeds | named exactly as the truth | other findings | tco_v within 3u | largest abs(z) of tco_v |")
    print("|---|---|---|---|---|---|")
    for label, (_, truth) in CASES.items():
        rows = [r for r in results if r[0] == label]
        exact = sum(set(r[2]) == truth for r in rows)
        other = sorted({e for r in rows for e in r[2]} - truth)
        zs = np.array([r[3] for r in rows if r[3] is not None])
        within = f"{int((np.abs(zs) <= 3).sum())}/{len(rows)}" if "thermal" in truth else "-"
        largest = f"{np.abs(zs).max():.2f}" if zs.size else "-"
        print(f"| {label} | {len(rows)} | {exact}/{len(rows)} | {', '.join(other) or 'none'} | {within} | {largest} |")


if __name__ == "__main__":
    main()
