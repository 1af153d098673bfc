"""Noise identification on seeded simulated recordings: for each noise
shape, datasets of the default plan (labelled table runs, CSV) simulated
with ``rotcal simulate --noise``, run through ingest, segmentation, fits
and ``rotcal.noise.identify_noise`` (or, ``--poses``, static poses whose
dwells are the residual pieces); per term, the fraction of channels
whose identified value lies within 3 u of the truth.

The truth a term is compared with is the drawn noise's IEEE terms
(``simulate.noise.noise_terms``) as the recording can show them: a
Gauss-Markov term whose Allan deviation peaks (at 1.89 T) beyond the longest
averaging time is, over the averaging times the recording has, a random
walk of K^2 = 2 q^2 / T (what it is for tau << T); one
shorter than 1.5 samples is white noise (q^2 (1 + a) / (1 - a) dt added to
N^2, a = exp(-dt / T)).

    python scripts/noise_identification.py --datasets 10 --out noise_identification.json
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np

from rotcal.blockwise.load import load
from rotcal.config import RunConfig
from rotcal.noise import NoiseModel, identify_noise
from rotcal.noise.model import identify_channel
from rotcal.run.stages import segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.noise import draw_channels, noise_terms
from rotcal.simulate.noise_request import parse_noise, resolve_noise

SHAPES = {
    "white": "white_sd=8",
    "ar_0.9": "white_sd=6,ar=0.9,ar_sd=4",
    "lowpass_0.1": "white_sd=8,lowpass_order=2,lowpass_cutoff=0.1",
    "lowpass_0.4": "white_sd=8,lowpass_order=2,lowpass_cutoff=0.4",
    "gauss_markov_10s": "white_sd=8,gauss_markov=10:4",
    "gauss_markov_100s": "white_sd=8,gauss_markov=100:2",
    "gauss_markov_1000s": "white_sd=8,gauss_markov=1000:4",
    "flicker": "white_sd=8,flicker_b=1",
    "random_walk": "white_sd=8,random_walk_k=0.1",
    "mix": "white_sd=6,ar=0.9,ar_sd=3,flicker_b=0.5,gauss_markov=100:2",
}


def observable_truth(terms: dict, dt: float, tau_max: float) -> dict[str, float | list]:
    """The truth as the recording shows it (module docstring)."""
    n2, k2 = terms["white_density"] ** 2, terms["random_walk"] ** 2
    gm = []
    for t, q in terms["gauss_markov"]:
        if 1.89 * t > tau_max:  # its Allan deviation peaks at 1.89 T: beyond the longest tau it rises as a random walk
            k2 += 2 * q * q / t
        elif t < 1.5 * dt:
            a = math.exp(-dt / t)
            n2 += q * q * (1 + a) / (1 - a) * dt
        else:
            gm.append((t, q))
    return {"white_density": math.sqrt(n2), "bias_instability": terms["bias_instability"], "random_walk": math.sqrt(k2),
            "gauss_markov": sorted(gm)}


POSES, POSE_SAMPLES, MOVE_SAMPLES, POSE_FS = 24, 500, 200, 100.0


def _poses_model(shape: str, seed: int) -> tuple[NoiseModel, dict]:
    """24 static poses of 5 s at 100 Hz, 2 s moves between them: the noise
    drawn on the whole grid, each pose's samples minus their mean (what a
    static recording's dwells give the identification)."""
    _, values = parse_noise(SHAPES[shape])
    noise = resolve_noise("", values, 1669.0, POSE_FS)
    period = POSE_SAMPLES + MOVE_SAMPLES
    drawn = draw_channels(noise, POSES * period, POSE_FS, np.random.default_rng(seed), 3)
    pieces = [drawn[k * period:k * period + POSE_SAMPLES] for k in range(POSES)]
    model = NoiseModel(tuple(identify_channel(c, [p[:, r] - p[:, r].mean() for p in pieces], POSE_FS, "bit")
                             for r, c in enumerate("uvw")), 1 / POSE_FS, "bit")
    return model, noise_terms(noise, POSE_FS)


def _table_model(shape: str, seed: int, work: Path) -> tuple[NoiseModel, dict]:
    """The default plan simulated, written as CSV, ingested, segmented and fitted."""
    spec = SimulationSpec().with_noise(SHAPES[shape])
    sim = simulate(spec, seed)
    path = write_dataset(sim, spec, work / f"{shape}_{seed}", "csv")
    ds = load(path, None, RunConfig())
    seg = segment_and_fit(ds, RunConfig())
    return identify_noise(seg.samples, seg.segments, seg.fits, seg.dwells, ds.meta.output_unit), sim.truth["noise"]["terms"]


def one(shape: str, seed: int, work: Path, poses: bool) -> list[dict]:
    model, terms = _poses_model(shape, seed) if poses else _table_model(shape, seed, work)
    rows = []
    for ch in model.channels:
        truth = observable_truth(terms, model.dt_s, float(ch.allan.tau_s[-1]))
        found = {(t.term, t.index): t for t in ch.terms}
        checks = {k: truth[k] for k in ("white_density", "bias_instability", "random_walk")}
        gm_found = sorted(((found[("gauss_markov_tau_s", j)], found[("gauss_markov_sd", j)]) for j in range(2)
                           if ("gauss_markov_tau_s", j) in found), key=lambda pair: pair[0].value)
        row = {"shape": shape, "seed": seed, "channel": ch.channel, "chi2_reduced": ch.chi2_reduced,
               "gauss_markov_found": len(gm_found), "gauss_markov_true": len(truth["gauss_markov"])}
        for term, value in checks.items():
            t = found.get((term, 0))
            row[term] = None if t is None else (t.value - value) / t.u
            row[f"shown_{term}"] = t is not None and t.value > 2 * t.u
        for j, (t_true, q_true) in enumerate(truth["gauss_markov"]):
            if j < len(gm_found):
                tt, tq = gm_found[j]
                row[f"gauss_markov_tau_s_{j}"] = (tt.value - t_true) / tt.u
                row[f"gauss_markov_sd_{j}"] = (tq.value - q_true) / tq.u
            else:
                row[f"gauss_markov_tau_s_{j}"] = row[f"gauss_markov_sd_{j}"] = None
        rows.append(row)
    return rows


TERMS = ("white_density", "bias_instability", "random_walk", "gauss_markov_tau_s_0", "gauss_markov_sd_0")


def markdown(rows: list[dict]) -> str:
    """Per shape and term: % of channels within 3 u (largest |z|), and for
    the power-law terms the % where the term is shown (value > 2 u)."""
    lines = ["| shape | channels | " + " | ".join(TERMS) + " | Gauss-Markov terms found / true |",
             "|---|---|" + "---|" * len(TERMS) + "---|"]
    for shape in dict.fromkeys(r["shape"] for r in rows):
        rs = [r for r in rows if r["shape"] == shape]
        cells = []
        for term in TERMS:
            z = [r[term] for r in rs if term in r]
            if not z:
                cells.append("-")
                continue
            found = [abs(v) for v in z if v is not None]
            cell = f"{100 * sum(v <= 3 for v in found) / len(z):.0f} % ({max(found, default=float('nan')):.1f})"
            shown = [r[f"shown_{term}"] for r in rs if f"shown_{term}" in r]
            cells.append(cell + (f", shown {100 * np.mean(shown):.0f} %" if shown else ""))
        found_gm = np.mean([r["gauss_markov_found"] for r in rs])
        lines.append(f"| {shape} | {len(rs)} | " + " | ".join(cells) + f" | {found_gm:.1f} / {rs[0]['gauss_markov_true']} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=10)
    parser.add_argument("--shapes", default=",".join(SHAPES))
    parser.add_argument("--out", type=Path, default=Path("noise_identification.json"))
    parser.add_argument("--poses", action="store_true", help="static poses (24 of 5 s at 100 Hz) instead of the table plan")
    args = parser.parse_args()
    rows: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        for shape in args.shapes.split(","):
            for seed in range(args.datasets):
                rows += one(shape, 1000 + seed, Path(tmp), args.poses)
            summary = {}
            for key in sorted({k for r in rows if r["shape"] == shape for k in r if not k.startswith("shown_")} - {"shape", "seed", "channel",
                                                                                    "chi2_reduced", "gauss_markov_found",
                                                                                    "gauss_markov_true"}):
                z = [r[key] for r in rows if r["shape"] == shape and key in r]
                found = [v for v in z if v is not None]
                # a true term the identification did not find counts as outside 3 u
                summary[key] = {"within_3u": float(np.mean([v is not None and abs(v) <= 3 for v in z])),
                                "missing": len(z) - len(found), "max_abs_z": float(np.max(np.abs(found))) if found else None}
            print(shape, json.dumps(summary), flush=True)
    args.out.write_text(json.dumps(rows, indent=1))
    print(markdown(rows))


if __name__ == "__main__":
    main()
