"""Issue 5's acceptance figures: 20 seeded continuous recordings of the
default test plan, reduced from t, u, v, w alone, clean (against the
labelled run of the same data and the truth) and with the logger's
time-base defects (against the truth). Prints the markdown pasted into
docs/measured.md.

    .venv/bin/python scripts/measure_unlabelled.py [--seeds 20]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rotcal.config import DiagnosisConfig, RunConfig  # noqa: E402
from rotcal.run import run_dataset  # noqa: E402
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset  # noqa: E402
from tests.unlabelled_checks import DEFECTS, check_seed  # noqa: E402


def _one(args: tuple[int, str | None]):
    seed, defects = args
    with tempfile.TemporaryDirectory() as work:
        return check_seed(seed, Path(work), defects, labelled=defects is None)


def benchmark(repeats: int = 5) -> str:
    """One continuous recording run labelled and unlabelled in this process
    (the diagnosis off: it needs table angles, so only the labelled run would
    pay for it): best of ``repeats`` each, and their ratio."""
    config = RunConfig(diagnosis=DiagnosisConfig(enabled=False))
    spec = SimulationSpec(plan=Plan(continuous=True))
    sim = simulate(spec, 7)
    with tempfile.TemporaryDirectory() as work:
        work = Path(work)
        data = {fmt: write_dataset(sim, spec, work / fmt, fmt) for fmt in ("csv", "csv-unlabelled")}
        best = {}
        for fmt, path in data.items():
            times = []
            for _ in range(repeats):
                start = time.perf_counter()
                run_dataset(path, work / f"out-{fmt}", config=config)
                times.append(time.perf_counter() - start)
            best[fmt] = min(times)
    return (f"run_dataset, {sim.samples.height} samples: labelled {best['csv']:.2f} s, unlabelled "
            f"{best['csv-unlabelled']:.2f} s (ratio {best['csv-unlabelled'] / best['csv']:.1f}, best of {repeats})")


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    seeds = range(100, 100 + args.seeds)
    start = time.perf_counter()
    with ProcessPoolExecutor(args.workers) as pool:
        clean = list(pool.map(_one, [(s, None) for s in seeds]))
        defect = list(pool.map(_one, [(s, DEFECTS) for s in seeds]))
    elapsed = time.perf_counter() - start
    for title, runs in (("clean, no [plan] rates", clean), (f"defects ({DEFECTS}), [plan] rates given", defect)):
        print(f"\n#### {title}: {len(runs)} seeds ({seeds.start}..{seeds.stop - 1})\n")
        print("| figure | value |\n|---|---|")
        print(f"| plan segments found | {sum(c.found for c in runs)} of {sum(c.expected for c in runs)} |")
        print(f"| other segments that are not rests | {sum(c.spurious for c in runs)} |")
        print(f"| largest boundary error | {max(c.boundary_s for c in runs):.3f} s |")
        print(f"| wrong axes | {sum(c.axis_errors for c in runs)} |")
        print(f"| largest relative rate error | {max(c.rate_rel for c in runs):.2e} |")
        if runs[0].vs_labelled:
            for rate in sorted(runs[0].vs_labelled):
                print(f"| rate {rate:g} Hz: max over seeds and parameters of abs(blind - labelled) / u | "
                      f"{max(c.vs_labelled[rate] for c in runs):.3f} |")
        rates = sorted({round(r, 6) for c in runs for r in c.z_truth})
        every = []
        for rate in rates:
            z = np.concatenate([v for c in runs for r, v in c.z_truth.items() if round(r, 6) == rate])
            every.append(z)
            print(f"| rate {rate:g} Hz: (value - truth) / u over {z.size} values | rms {np.sqrt(np.mean(z**2)):.2f}, "
                  f"largest {np.abs(z).max():.2f}, beyond 3: {int((np.abs(z) > 3).sum())} |")
        z = np.concatenate(every)
        print(f"| all rates: (value - truth) / u over {z.size} values | rms {np.sqrt(np.mean(z**2)):.2f}, "
              f"beyond 3: {int((np.abs(z) > 3).sum())} ({100 * np.mean(np.abs(z) > 3):.2f} %; 0.27 % expected) |")
        if "clock_drift_ppm" in runs[0].timebase["truth"] and runs[0].timebase["truth"]["clock_drift_ppm"]:
            for check, key, scale, unit in (("duplicated_samples", "duplicated_records", 1, ""),
                                            ("repeated_stamps", "repeated_stamps", 1, ""),
                                            ("missing_samples", "missing_samples", 1, ""),
                                            ("timestamp_jitter", "jitter_realised_s", 1e3, " ms"),
                                            ("clock_drift", "clock_drift_ppm", 1, " ppm")):
                pairs = [(c.timebase["reported"][check][1] * (scale if check != "clock_drift" else 1),
                          c.timebase["truth"][key] * (scale if check != "clock_drift" else 1)) for c in runs]
                diff = np.array([a - b for a, b in pairs])
                detected = sum(c.timebase["reported"][check][0] for c in runs)
                print(f"| {check}: reported - true (detected in {detected} of {len(runs)}) | "
                      f"mean {diff.mean():.3g}{unit}, largest {np.abs(diff).max():.3g}{unit} |")
    print(f"\n({elapsed:.0f} s on {args.workers} workers)")
    print(benchmark())


if __name__ == "__main__":
    main()
