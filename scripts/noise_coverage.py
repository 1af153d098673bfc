"""Uncertainties and false findings under coloured noise: for each noise
shape, seeded default-plan table datasets (labelled segment files, or
``--recording unlabelled``: t, u, v, w only in one file, no ``[plan]``
rates) through rotcal's stages, and per parameter class (s, phi, O) and rate the sd of
the normalised errors z = (estimate - truth) / u and the fraction |z| <= 2
(baseline results; the simultaneous solution's too), and the clean
datasets' finding rates (any catalogue finding; any finding at all).

    python scripts/noise_coverage.py [--datasets 50] [--diagnosed 50] [--workers 2] [--shapes white,ar09,...] [--out FILE.jsonl]

``--shapes`` also takes the ``UNSEEN`` shapes, which no test draws.
        [--recording labelled|unlabelled]
    python scripts/noise_coverage.py --summarise FILE.jsonl

The shapes are drawn by the simulator's noise model (``rotcal simulate
--noise``, ``rotcal.simulate.noise``) over the DUT's 8 counts of white
noise; the Gauss-Markov shape draws its sd (0.1 to 0.5 of the white sd)
and time constant (10 to 1000 s, log-uniform) per dataset. The true g of
each dataset is drawn from N(g_local, u(g)^2), as in
``rotcal.metrology.coverage``. An unlabelled recording's rates are those
rotcal measured (the phase-free and dwell reductions, ``combine.unreferenced``;
no simultaneous solution: it needs the table angle), each named by the
nearest nominal rate of the plan. Prints a Markdown table; ``--out`` also
writes the per-dataset figures as JSON. About 1.5 s a dataset without the
diagnosis and 6 s with it on one core.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from rotcal.config import RunConfig, RunSection
from rotcal.ingest.dataset import load_dataset
from rotcal.metrology.simultaneous import simultaneous
from rotcal.model.physics import INTRINSIC
from rotcal.model.results import IntrinsicResult
from rotcal.run.recommended import diagnose_stage
from rotcal.run.stages import determined, reduce, segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset

WHITE_SD = 8.0  # the default DUT's white noise (counts)
CLASSES = {"s": (0, 1, 2), "phi": (3, 4, 5), "O": (6, 7, 8)}
RECORDINGS = ("labelled", "unlabelled")


def noise_request(shape: str, seed: int) -> str:
    """The simulator's ``--noise`` request of a shape (counts, seconds)."""
    rng = np.random.default_rng([seed, 0x4E5])
    gm_sd = WHITE_SD * rng.uniform(0.1, 0.5)
    gm_tau = float(np.exp(rng.uniform(np.log(10.0), np.log(1000.0))))
    return {
        "white": "",
        "ar09": f"white_sd={WHITE_SD},ar=0.9,ar_sd={WHITE_SD}",
        "lowpass01": f"white_sd={WHITE_SD},lowpass_order=2,lowpass_cutoff=0.1",
        "lowpass04": f"white_sd={WHITE_SD},lowpass_order=2,lowpass_cutoff=0.4",
        "gauss_markov": f"white_sd={WHITE_SD},gauss_markov={gm_tau:.1f}:{gm_sd:.2f}",
        "flicker": f"white_sd={WHITE_SD},flicker_b=2",
        "random_walk": f"white_sd={WHITE_SD},random_walk_k=0.05",
        "mix": "white_sd=6,ar=0.5,ar_sd=4,lowpass_order=2,lowpass_cutoff=0.4,gauss_markov=300:2,flicker_b=1,random_walk_k=0.02",
        **UNSEEN,
    }[shape]


# shapes no test draws (``--shapes ar2,gm_fast,...``): what a recording from elsewhere may hold
UNSEEN = {
    "ar2": "white_sd=6,ar=1.2;-0.4,ar_sd=6",
    "gm_fast": "white_sd=6,gauss_markov=1.0:6",
    "quant": "white_sd=1.5,quantization=4",
    "lp4": "white_sd=8,lowpass_order=4,lowpass_cutoff=0.05",
    "flicker5": "white_sd=6,flicker_b=5",
    "gm30": "white_sd=8,gauss_markov=30:3",
    "gm1000": "white_sd=8,gauss_markov=1000:3",
    "gm3000": "white_sd=8,gauss_markov=3000:3",
    "gm2": "white_sd=6,gauss_markov=30:3;2000:3",
}


SHAPES = ("white", "ar09", "lowpass01", "lowpass04", "gauss_markov", "flicker", "random_walk", "mix")


def z_of(results: list[IntrinsicResult], truth: np.ndarray, nominal: tuple[float, ...] = ()) -> dict[str, list[float]]:
    """Each result's normalised errors by its rate's name: the rate itself,
    or (``nominal`` given) the nearest of those rates."""
    def name(rate: float) -> str:
        return f"{min(nominal, key=lambda q: abs(q - abs(rate))) if nominal else rate:g}"

    named = {name(r.rate_hz): ((r.value - truth) / r.std_uncertainty).tolist() for r in results}
    if len(named) < len(results):
        raise ValueError(f"two measured rates nearest one nominal rate: {[r.rate_hz for r in results]}")
    return named


def case(args: tuple[str, int, bool, str]) -> dict:
    """One dataset: baseline and simultaneous z per rate, and (``diagnosed``) its findings."""
    shape, seed, diagnosed, recording = args
    request = noise_request(shape, seed)
    spec = SimulationSpec().with_noise(request) if request else SimulationSpec()
    rng = np.random.default_rng([seed, 0x67])
    true_spec = replace(spec, g_local=spec.g_local + spec.g_local_uncertainty * rng.standard_normal())
    sim = simulate(true_spec, seed)
    truth = np.array([sim.truth["intrinsic"][p] for p in INTRINSIC])
    config = RunConfig(run=RunSection(workers=1))
    with tempfile.TemporaryDirectory(prefix="rotcal-noise-") as tmp:
        labelled = recording == "labelled"
        path = write_dataset(sim, spec, Path(tmp) / f"{shape}{seed}", "csv" if labelled else "csv-unlabelled")
        if not labelled:  # no nominal rates: rotcal finds the segments and rates from the signals alone
            toml = path / "dataset.toml"
            toml.write_text(toml.read_text().split("\n[plan]")[0])
        ds = load_dataset(path)
        seg = segment_and_fit(ds, config)
        reductions = reduce(seg, ds)
        results, _, _ = determined(reductions, seg, path)
        simult = [r for r in simultaneous(seg.samples, seg.labelled_fits, ds.meta.g_local, ds.meta.g_local_uncertainty,
                                          sums=seg.sums) if isinstance(r, IntrinsicResult)]
        nominal = () if labelled else (0.0, *spec.plan.rates_hz)
        out = {"shape": shape, "seed": seed, "noise": request, "baseline": z_of(list(results), truth, nominal),
               "simultaneous": z_of(simult, truth, nominal)} | ({} if labelled else {"recording": recording})
        if diagnosed:
            diagnosis, _ = diagnose_stage(seg, reductions, results, ds, config)
            found = [] if diagnosis is None else diagnosis.findings.filter(diagnosis.findings["detected"])["effect"].to_list()
            out["findings"] = found
    return out


def summary(rows: list[dict], source: str) -> list[tuple]:
    """(shape, class, rate, datasets, sd of z, fraction |z| <= 2) per shape, class and rate."""
    table = []
    for shape in dict.fromkeys(r["shape"] for r in rows):
        mine = [r[source] for r in rows if r["shape"] == shape]
        rates = sorted({rate for r in mine for rate in r}, key=float)
        for cls, idx in CLASSES.items():
            for rate in rates:
                z = np.array([r[rate] for r in mine if rate in r])[:, list(idx)]
                table.append((shape, cls, rate, z.shape[0], float(np.sqrt(np.mean(z**2))), float(np.mean(np.abs(z) <= 2))))
    return table


def markdown(rows: list[dict], source: str) -> str:
    lines = ["| shape | class | rate (Hz) | datasets | sd of z | within 2 u |", "|---|---|---|---|---|---|"]
    for shape, cls, rate, n, sd, within in summary(rows, source):
        flag = "" if 0.8 <= sd <= 1.25 else " **"
        lines.append(f"| {shape} | {cls} | {rate} | {n} | {sd:.2f}{flag} | {100 * within:.0f} % |")
    return "\n".join(lines)


def compact_markdown(rows: list[dict], source: str) -> str:
    """One row per shape: each class's sd of z at every rate (rates ascending) and its fraction within 2 u."""
    table = summary(rows, source)
    if not table:
        return "(none)"
    rates = sorted({t[2] for t in table}, key=float)
    lines = [f"| shape | datasets | s: sd of z at {', '.join(rates)} Hz | phi | O |", "|---|---|---|---|---|"]
    for shape in dict.fromkeys(t[0] for t in table):
        cells = []
        for cls in CLASSES:
            mine = [t for t in table if t[0] == shape and t[1] == cls]
            cells.append(" ".join(f"{t[4]:.2f}" for t in mine) + f" ({100 * np.mean([t[5] for t in mine]):.0f} % within 2 u)")
        n = max(t[3] for t in table if t[0] == shape)
        lines.append(f"| {shape} | {n} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def findings_markdown(rows: list[dict]) -> str:
    lines = ["| shape | datasets | any catalogue finding | any finding | effects named (count) |", "|---|---|---|---|---|"]
    for shape in dict.fromkeys(r["shape"] for r in rows):
        mine = [r["findings"] for r in rows if r["shape"] == shape and "findings" in r]
        if not mine:
            continue
        catalogue = sum(any(e != "unexplained" for e in f) for f in mine)
        anything = sum(bool(f) for f in mine)
        names: dict[str, int] = {}
        for f in mine:
            for e in set(f):
                names[e] = names.get(e, 0) + 1
        named = ", ".join(f"{e} ({k})" for e, k in sorted(names.items(), key=lambda x: -x[1]))
        lines.append(f"| {shape} | {len(mine)} | {100 * catalogue / len(mine):.0f} % | {100 * anything / len(mine):.0f} % | {named or '-'} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=50)
    parser.add_argument("--diagnosed", type=int, default=50, help="of them, how many also diagnosed")
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--shapes", default=",".join(SHAPES))
    parser.add_argument("--recording", choices=RECORDINGS, default="labelled",
                        help="labelled segment files, or t, u, v, w only in one file without [plan] rates")
    parser.add_argument("--out", type=Path, help="the per-dataset figures, one JSON line each, written as they come")
    parser.add_argument("--summarise", type=Path, help="print the tables of such a file (of a run still going, too)")
    args = parser.parse_args()
    if args.summarise:
        report([json.loads(line) for line in args.summarise.read_text().splitlines() if line.strip()], 0.0)
        return
    shapes = args.shapes.split(",")
    # seed by seed across the shapes: a run stopped early still covers every shape alike
    jobs = [(shape, args.first_seed + k, k < args.diagnosed, args.recording) for k in range(args.datasets) for shape in shapes]
    start = time.perf_counter()
    out = args.out.open("w") if args.out else None
    rows = []
    with ProcessPoolExecutor(max(args.workers, 1), mp_context=multiprocessing.get_context("spawn")) as pool:
        # spawned: a fork after polars' thread pool started deadlocks
        for row in pool.map(case, jobs):
            rows.append(row)
            if out:
                out.write(json.dumps(row) + "\n")
                out.flush()
    report(rows, time.perf_counter() - start)


def report(rows: list[dict], seconds: float) -> None:
    print(f"{len(rows)} datasets in {seconds:.0f} s\n")
    print("Per shape (sd of z per rate; fraction within 2 u over the rates), baseline:\n")
    print(compact_markdown(rows, "baseline"))
    print("\nSimultaneous solution:\n")
    print(compact_markdown(rows, "simultaneous"))
    print("\nBaseline (per-segment fits, combined):\n")
    print(markdown(rows, "baseline"))
    print("\nSimultaneous solution:\n")
    print(markdown(rows, "simultaneous"))
    print("\nClean-dataset findings:\n")
    print(findings_markdown(rows))


if __name__ == "__main__":
    main()
