"""Regenerate issue 4's figures: false alarms on clean datasets, detection
and naming of every catalogue effect alone and in pairs, parameter errors,
refined against baseline, unexplained structures, and the Gaitan 2021 case.

    python scripts/diagnosis_acceptance.py [--seeds 10] [--clean 20] [--workers 2] [--out DIR]
    python scripts/diagnosis_acceptance.py --noise mix --upper --singles   # catalogue effects under coloured noise

Sizes are drawn across the ranges of docs/effects.md (each catalogue effect's ``sizes``, rotcal.diagnose.scenarios);
``--upper``: across the upper two thirds. ``--noise SHAPE``: the DUT's noise of ``noise_coverage.py``'s shapes
(white by default); ``--singles``: clean datasets and single effects only.
Prints a Markdown report (the tables in docs/measured.md come from it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import RunConfig, RunSection
from rotcal.diagnose.scenarios import draw_effect, draw_foreign
from rotcal.model.effects import names
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset

sys.path.insert(0, str(Path(__file__).resolve().parent))
from noise_coverage import SHAPES, noise_request  # noqa: E402 (the script beside this one)

PAIRS = (("centripetal", "channel_delay"), ("cubic_nonlinearity", "axis_tilt"),
         ("quadratic_nonlinearity", "rate_ripple"), ("offset_drift", "axis_tilt"), ("rate_error", "clipping"))


RECORDINGS = ("labelled", "unlabelled", "continuous")


def case(args: tuple) -> dict:
    """Simulate one dataset, run rotcal on it, and compare with the truth.
    An optional sixth element names the recording (``RECORDINGS``): labelled
    segment files (the default), or t, u, v, w only in one file, of the
    plan's segments or of a continuous recording (transitions, ramps, hand
    reorientations), without ``[plan]`` rates."""
    label, seed, effects, foreign, workdir, *how = args
    recording = how[0] if how else "labelled"
    noise = how[1] if len(how) > 1 else ""  # the simulator's --noise request
    spec = SimulationSpec().with_effects(*effects).with_foreign(*foreign)
    spec = spec.with_noise(noise) if noise else spec
    if recording == "continuous":
        spec = replace(spec, plan=replace(spec.plan, continuous=True))
    data = Path(workdir) / f"{label}_{seed}"
    if not (data / "out" / "intrinsic.parquet").is_file():  # a run published in a kept ``workdir`` is read back
        write_dataset(simulate(spec, seed), spec, data / "data", "csv" if recording == "labelled" else "csv-unlabelled")
        if recording != "labelled":  # no nominal rates: the recording alone
            toml = data / "data" / "dataset.toml"
            toml.write_text(toml.read_text().split("\n[plan]")[0])
        run_dataset(data / "data", data / "out", config=RunConfig(run=RunSection(workers=1)))
    truth = json.loads((data / "data" / "truth.json").read_text())
    findings = pl.read_parquet(data / "out" / "diagnosis.parquet").filter(pl.col("detected"))
    params = pl.read_parquet(data / "out" / "effect_parameters.parquet")
    intrinsic = pl.read_parquet(data / "out" / "intrinsic.parquet")
    true_values = truth["intrinsic"]
    z = intrinsic.with_columns(z=(pl.col("value") - pl.col("parameter").replace_strict(true_values)) / pl.col("std_uncertainty"))
    param_z = []
    for eff in truth["effects"]:
        for name, value in eff["parameters"].items():
            row = params.filter((pl.col("effect") == eff["effect"]) & (pl.col("parameter") == name)
                                & (pl.col("axis") == eff["axis"]))
            if row.height:
                u = row["std_uncertainty"][0]
                if eff["effect"] == "clipping":
                    u = max(u, 1.0)
                param_z.append((eff["effect"], name, float((row["value"][0] - value) / u)))
            else:
                param_z.append((eff["effect"], name, None))
    return {
        "label": label, "seed": seed, "recording": recording, "effects": effects, "foreign": foreign,
        "named": sorted(set(findings["effect"].to_list())),
        "where": findings["where"].to_list(), "evidence": findings["evidence"].to_list(),
        "param_z": param_z,
        "biased": _biased(z),
        "refined_z": _refined_z(z),
        "baseline_z": z.filter(pl.col("model") == "baseline").select("rate_hz", "parameter", "z").rows(),
        "truth_effects": truth["effects"], "truth_foreign": truth["foreign"],
    }


def _biased(z: pl.DataFrame) -> tuple[int, int, float, list]:
    """(parameters whose baseline lies beyond 3u of the truth, how many of
    them the refined model puts within 3u, the largest refined |z| among them,
    and those left beyond 3u as (rate, parameter, refined z))."""
    wide = z.pivot("model", index=["rate_hz", "parameter"], values="z")
    if "refined" not in wide.columns:
        return int((wide["baseline"].abs() > 3).sum()), 0, float("nan"), []
    beyond = wide.filter(pl.col("baseline").abs() > 3)
    left = beyond.filter(pl.col("refined").abs() > 3).select("rate_hz", "parameter", "refined").rows()
    return beyond.height, int((beyond["refined"].abs() <= 3).sum()), float(beyond["refined"].abs().max() or 0.0), left


def _refined_z(z: pl.DataFrame) -> list[float]:
    """Every refined parameter's normalised error (none without a refined model)."""
    return z.filter(pl.col("model") == "refined")["z"].to_list()


def twin_z(result: dict, workdir: str) -> list[tuple]:
    """The parameters a refined model leaves beyond 3u, against the same
    seed simulated without the effect (the same noise): (rate, parameter,
    refined z, clean baseline z). Equal values say the noise, not the
    effect's modelling, put the refined value there."""
    if not result["biased"][3]:
        return []
    clean = case(("twin", result["seed"], (), (), workdir, result["recording"]))
    wide = {(r, p): z for r, p, z in clean["baseline_z"]}
    rates = {r for r, _ in wide}
    # without nominal rates each rate is named by its measured mean, which differs between the two simulations
    return [(r, p, z, wide[(min(rates, key=lambda q: abs(q - r)), p)]) for r, p, z in result["biased"][3]]


def scenarios(n_seeds: int, n_clean: int, workdir: str, shape: str = "white", part: tuple[float, float] = (0.0, 1.0),
              singles: bool = False) -> list[tuple]:
    def noise(seed: int) -> tuple[str, str]:
        return ("labelled", noise_request(shape, seed))

    jobs = [("clean", 1000 + s, (), (), workdir, *noise(1000 + s)) for s in range(n_clean)]
    for k, name in enumerate(names()):
        for s in range(n_seeds):
            rng = np.random.default_rng([k, s])
            jobs.append((name, 2000 + 100 * k + s, (draw_effect(name, rng, part),), (), workdir, *noise(2000 + 100 * k + s)))
    if singles:
        return jobs
    for k, pair in enumerate(PAIRS):
        for s in range(n_seeds):
            rng = np.random.default_rng([100 + k, s])
            jobs.append(("+".join(pair), 5000 + 100 * k + s, tuple(draw_effect(n, rng, part) for n in pair), (), workdir,
                         *noise(5000 + 100 * k + s)))
    for k, name in enumerate(("tone", "offset_step")):
        for s in range(n_seeds):
            rng = np.random.default_rng([200 + k, s])
            jobs.append((name, 8000 + 100 * k + s, (), (draw_foreign(name, rng),), workdir, *noise(8000 + 100 * k + s)))
    for s in range(n_seeds):
        jobs.append(("gaitan", 9000 + s, (f"centripetal:axis={'xyz'[s % 3]},radius_m=0.22",), (), workdir, *noise(9000 + s)))
    return jobs


def summarise_refined(results: list[dict], twins: list[tuple]) -> str:
    """Refined normalised errors over every parameter of every dataset with
    a refined model, and the twins of those a refined model leaves beyond 3u."""
    zs = np.array([z for r in results for z in r["refined_z"]])
    if zs.size == 0:
        return "no refined models"
    lines = [f"Refined parameters of {sum(bool(r['refined_z']) for r in results)} datasets: {zs.size} normalised errors, "
             f"RMS {np.sqrt(np.mean(zs ** 2)):.3f}, {int((np.abs(zs) > 3).sum())} beyond 3 "
             f"({100 * np.mean(np.abs(zs) > 3):.2f} %; 0.27 % for a standard normal)."]
    if twins:
        lines += ["", "Parameters whose baseline was beyond 3u and whose refined value is still beyond 3u, "
                  "against the same seed simulated without the effect (same noise):", "",
                  "| scenario | seed | rate (Hz) | parameter | refined z | clean baseline z (same noise) |", "|---|---|---|---|---|---|"]
        lines += [f"| {label} | {seed} | {r:g} | {p} | {z:+.2f} | {zc:+.2f} |" for label, seed, (r, p, z, zc) in twins]
    return "\n".join(lines)


def summarise(results: list[dict]) -> str:
    lines = ["| scenario | datasets | correctly named | named with no other catalogue finding | other findings "
             "| effect parameters within 3u | refined within 3u / parameters whose baseline was beyond 3u |",
             "|---|---|---|---|---|---|---|"]
    by_label: dict[str, list[dict]] = {}
    for r in results:
        by_label.setdefault(r["label"], []).append(r)
    for label, rs in by_label.items():
        if label == "clean":
            anything = sum(bool(r["named"]) for r in rs)
            catalogue = sum(bool(set(r["named"]) - {"unexplained"}) for r in rs)
            lines.append(f"| clean | {len(rs)} | - | - | {anything} datasets with a finding ({catalogue} catalogue) | - | - |")
            continue
        expected = set(label.split("+")) if label not in ("tone", "offset_step") else {"unexplained"}
        if label == "gaitan":
            expected = {"centripetal"}
        named = sum(expected <= set(r["named"]) for r in rs)
        alone = sum(expected <= set(r["named"]) and not set(r["named"]) - expected - {"unexplained"} for r in rs)
        other = sum(bool(set(r["named"]) - expected) for r in rs)
        zs = [abs(z) for r in rs for (_, _, z) in r["param_z"] if z is not None]
        missing = sum(z is None for r in rs for (_, _, z) in r["param_z"])
        within = f"{sum(z <= 3 for z in zs)}/{len(zs)}" + (f" ({missing} not reported)" if missing else "") if zs or missing else "-"
        beyond = sum(r["biased"][0] for r in rs)
        fixed = sum(r["biased"][1] for r in rs)
        worst = max((r["biased"][2] for r in rs if r["biased"][0]), default=float("nan"))
        lines.append(f"| {label} | {len(rs)} | {named} | {alone} | {other} | {within} | {fixed}/{beyond} (largest refined |z| {worst:.2f}) |")
    return "\n".join(lines)


def run_cases(jobs: list[tuple], workdir: str, workers: int) -> tuple[list[dict], list[tuple]]:
    """Every job's ``case`` on a pool of ``workers``, then ``twin_z`` for the
    cases whose refined values stay beyond 3u: (results, twins)."""
    with ProcessPoolExecutor(workers) as pool:
        results = list(pool.map(case, jobs))
        left = [r for r in results if r["biased"][3]]
        twins = [(r["label"], r["seed"], t) for r, ts in zip(left, pool.map(twin_z, left, [workdir] * len(left)))
                 for t in ts]
    return results, twins


def arguments(doc: str) -> argparse.ArgumentParser:
    """The options every diagnosis acceptance script takes."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--clean", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", type=Path, help="also write every case's details here")
    parser.add_argument("--noise", choices=SHAPES, default="white", help="the DUT's noise (noise_coverage.py's shapes)")
    parser.add_argument("--upper", action="store_true", help="effect sizes in the upper two thirds of their ranges")
    parser.add_argument("--singles", action="store_true", help="clean datasets and single effects only")
    return parser


def main() -> None:
    args = arguments(__doc__).parse_args()
    with tempfile.TemporaryDirectory() as workdir:
        jobs = scenarios(args.seeds, args.clean, workdir, args.noise, (1 / 3, 1.0) if args.upper else (0.0, 1.0), args.singles)
        results, twins = run_cases(jobs, workdir, args.workers)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    print(summarise(results))
    print()
    print(summarise_refined(results, twins))
    print()
    for r in results:
        expected = set(r["label"].split("+")) if r["label"] not in ("tone", "offset_step", "gaitan", "clean") else None
        if r["label"] == "clean" and r["named"] or expected is not None and set(r["named"]) != expected:
            print(f"- {r['label']} seed {r['seed']} {r['effects']} {r['foreign']}: named {r['named']}: {r['evidence']}")


if __name__ == "__main__":
    main()
