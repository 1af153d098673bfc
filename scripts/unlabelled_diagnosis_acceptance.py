"""Regenerate issue 15 item 1's figures: the diagnosis of recordings without
table angles (t, u, v, w only, the default plan, no ``[plan]`` rates), on
clean datasets, every catalogue effect such a recording can show alone, and
pairs; sizes from the upper two thirds of each effect's range (its
``sizes``: docs/effects.md).

    nice python scripts/unlabelled_diagnosis_acceptance.py [--seeds 10] [--clean 20] [--workers 2]
        [--recording unlabelled|continuous] [--only LABEL ...] [--workdir DIR [--done-only]] [--json FILE]

Each dataset is simulated and run by ``diagnosis_acceptance.case`` (issue
4's machinery) as an unlabelled (or continuous) recording. Prints a
Markdown report (docs/measured.md's section comes from it).
"""

from __future__ import annotations

import json
import sys
import tempfile
from contextlib import nullcontext
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from diagnosis_acceptance import arguments, run_cases, summarise_refined  # noqa: E402 (the script beside this one)

from rotcal.diagnose.scenarios import draw_effect  # noqa: E402
from rotcal.model.effects import effect_named, names  # noqa: E402

UPPER = (1 / 3, 1.0)  # the upper two thirds of each effect's size range
PAIRS = (("centripetal", "channel_delay"), ("cubic_nonlinearity", "axis_tilt"),
         ("offset_drift", "quadratic_nonlinearity"), ("centripetal", "clipping"))


def shown() -> tuple[str, ...]:
    """The catalogue effects an unlabelled recording of t, u, v, w can show:
    not those the reconstructed angles absorb, nor those needing a logged
    column it lacks (``thermal``: temperature_c)."""
    return tuple(n for n in names() if not effect_named(n).absorbed_by_own_phase and not effect_named(n).needs)


def scenarios(n_seeds: int, n_clean: int, workdir: str, recording: str) -> list[tuple]:
    jobs = [("clean", 11000 + s, (), (), workdir, recording) for s in range(n_clean)]
    for k, name in enumerate(shown()):
        for s in range(n_seeds):
            rng = np.random.default_rng([300 + k, s])
            jobs.append((name, 12000 + 100 * k + s, (draw_effect(name, rng, UPPER),), (), workdir, recording))
    for k, pair in enumerate(PAIRS):
        for s in range(n_seeds):
            rng = np.random.default_rng([400 + k, s])
            jobs.append(("+".join(pair), 15000 + 100 * k + s, tuple(draw_effect(n, rng, UPPER) for n in pair), (),
                         workdir, recording))
    return jobs


def summarise(results: list[dict]) -> str:
    """Per scenario: datasets, named with no other finding, named (others
    allowed), effect parameters within 3u among the named cases."""
    lines = ["| scenario | datasets | named, no other finding | named | effect parameters within 3u (named cases) |",
             "|---|---|---|---|---|"]
    single = exact_single = 0
    for label in dict.fromkeys(r["label"] for r in results):
        rs = [r for r in results if r["label"] == label]
        if label == "clean":
            lines.append(f"| clean | {len(rs)} | - | {sum(bool(r['named']) for r in rs)} with any finding | - |")
            continue
        expected = set(label.split("+"))
        exact = sum(set(r["named"]) == expected for r in rs)
        named = [r for r in rs if expected <= set(r["named"])]
        zs = [abs(z) for r in named for (_, _, z) in r["param_z"] if z is not None]
        within = f"{sum(z <= 3 for z in zs)}/{len(zs)}" if zs else "-"
        lines.append(f"| {label} | {len(rs)} | {exact} | {len(named)} | {within} |")
        if "+" not in label:
            single, exact_single = single + len(rs), exact_single + exact
    lines += ["", f"Single-effect datasets named with no other finding: {exact_single}/{single} "
              f"({100 * exact_single / max(single, 1):.0f} %)."]
    return "\n".join(lines)


def main() -> None:
    parser = arguments(__doc__)
    parser.add_argument("--recording", choices=("unlabelled", "continuous"), default="unlabelled")
    parser.add_argument("--only", nargs="*", help="only these scenario labels")
    parser.add_argument("--workdir", type=Path, help="keep the datasets here (those already run are read back)")
    parser.add_argument("--done-only", action="store_true", help="only the datasets already run in --workdir")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() if args.workdir is None else nullcontext(str(args.workdir)) as workdir:
        jobs = [j for j in scenarios(args.seeds, args.clean, workdir, args.recording)
                if (not args.only or j[0] in args.only)
                and (not args.done_only or (Path(workdir) / f"{j[0]}_{j[1]}" / "out" / "intrinsic.parquet").is_file())]
        results, twins = run_cases(jobs, workdir, args.workers)
    if args.json:
        args.json.write_text(json.dumps(results, indent=1, default=str))
    print(f"Recording: {args.recording}, t, u, v, w only, no [plan] rates; effects tested: {', '.join(shown())}.")
    print()
    print(summarise(results))
    print()
    print(summarise_refined(results, twins))
    print()
    for r in results:
        expected = set() if r["label"] == "clean" else set(r["label"].split("+"))
        if set(r["named"]) != expected:
            print(f"- {r['label']} seed {r['seed']} {r['effects']}: named {r['named']}: {r['evidence']}")


if __name__ == "__main__":
    main()
