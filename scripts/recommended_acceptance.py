"""Regenerate issue 14's second acceptance figures: on datasets with one
catalogue effect each, at mid-range sizes, calibration.json validates
against its schema, the recommended rows are the refined ones wherever the
diagnosis detects the effect, and how many recommended values lie beyond
3u of the truth.

    nice python scripts/recommended_acceptance.py [--seeds 10] [--workers 2] [--json FILE]

Each dataset is simulated and run by ``diagnosis_acceptance.case`` (the
same machinery as issue 4's figures); the sizes are drawn from the middle
half of each effect's range (its ``sizes``: docs/effects.md). Prints a
Markdown report (docs/measured.md's section comes from it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diagnosis_acceptance import case  # noqa: E402 (the script beside this one)

from rotcal.errors import InputError  # noqa: E402
from rotcal.model.calibration import Calibration  # noqa: E402
from rotcal.model.effects import effect_named, names  # noqa: E402
from rotcal.model.physics import AXES  # noqa: E402

MID = (0.25, 0.75)  # the middle half of each effect's size range


def draw_mid(name: str, rng: np.random.Generator) -> str:
    """One effect of ``name`` with its size in the middle half of its range
    (as ``diagnose.scenarios.draw_effect`` draws across the whole range)."""
    effect = effect_named(name)
    low, high = effect.sizes
    size = low + (high - low) * rng.uniform(*MID)
    return effect.draw(size, rng.choice([-1.0, 1.0]), rng.choice(AXES), rng.choice(("u", "v", "w")), rng)


def checked(job: tuple) -> dict:
    """One dataset through ``case``, then its calibration.json and recommended rows against the truth."""
    result = case(job)
    label, seed, _, _, workdir = job
    data = Path(workdir) / f"{label}_{seed}"
    try:
        calibration, schema_error = Calibration.read(data / "out"), None
    except InputError as exc:
        calibration, schema_error = None, str(exc)
    truth = json.loads((data / "data" / "truth.json").read_text())["intrinsic"]
    intrinsic = pl.read_parquet(data / "out" / "intrinsic.parquet")
    recommended = intrinsic.filter(pl.col("recommended"))
    z = ((recommended["value"] - recommended["parameter"].replace_strict(truth)) / recommended["std_uncertainty"]).abs()
    models = sorted(set(recommended["model"].to_list()))
    document_models = sorted({r.model for r in calibration.rates}) if calibration else []
    return {**result, "schema_error": schema_error, "recommended": models, "document_models": document_models,
            "reason": calibration.rates[0].reason if calibration else None,
            "values": recommended.height, "beyond_3u": int((z > 3).sum()), "max_z": float(z.max() or 0.0),
            "beyond": recommended.filter(z > 3).select("rate_hz", "parameter").rows()}


def summarise(results: list[dict]) -> str:
    lines = ["| effect | datasets | calibration.json valid | detected | recommended = refined where detected "
             "| recommended values | beyond 3u | largest \\|z\\| |", "|---|---|---|---|---|---|---|---|"]
    for label in dict.fromkeys(r["label"] for r in results):
        rs = [r for r in results if r["label"] == label]
        detected = [r for r in rs if label in r["named"]]
        refined = sum(r["recommended"] == r["document_models"] == ["refined"] for r in detected)
        lines.append(f"| {label} | {len(rs)} | {sum(r['schema_error'] is None for r in rs)} | {len(detected)} "
                     f"| {refined}/{len(detected)} | {sum(r['values'] for r in rs)} | {sum(r['beyond_3u'] for r in rs)} "
                     f"| {max(r['max_z'] for r in rs):.2f} |")
    values, beyond = sum(r["values"] for r in results), sum(r["beyond_3u"] for r in results)
    lines += ["", f"All: {len(results)} datasets, {values} recommended values, {beyond} beyond 3u of the truth "
              f"({100 * beyond / max(values, 1):.2f} %; at most 1 % accepted, 0.27 % for a standard normal)."]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--json", type=Path, help="also write every case's details here")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as workdir:
        jobs = [(name, 12000 + 100 * k + s, (draw_mid(name, np.random.default_rng([300 + k, s])),), (), workdir)
                for k, name in enumerate(names()) for s in range(args.seeds)]
        with ProcessPoolExecutor(args.workers) as pool:
            results = list(pool.map(checked, jobs))
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    print(summarise(results))
    print()
    for r in results:
        if r["schema_error"] or (r["label"] in r["named"]) != (r["recommended"] == ["refined"]) or r["beyond_3u"]:
            print(f"- {r['label']} seed {r['seed']} {r['effects']}: named {r['named']}, recommended {r['recommended']} "
                  f"({r['reason']}), beyond 3u {r['beyond']}{'; ' + r['schema_error'] if r['schema_error'] else ''}")


if __name__ == "__main__":
    main()
