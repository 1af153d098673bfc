"""The batch acceptance of degenerate recordings (docs/fuzzing.md,
"Degenerate recordings"): ``rotcal batch`` over ``--good`` good small-plan
table datasets and one dataset of each degenerate kind of
``degenerate_inputs`` (the quantized ones at 1000 counts; and a static
recording whose signed 32-bit output wraps around at 2^31). Every good dataset must be published within
``Z_MAX`` uncertainties of its truth with no finding; every degenerate one
published so too, or quarantined with a one-line reason; no error; the
exit status 4 (some quarantined, docs/batch.md); all within ``--timeout``
seconds (else a hang).

    python scripts/degenerate_batch.py --good 20 --workers 2 --report batch.txt

Exit status 0 when the acceptance holds, 1 otherwise.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import polars as pl

sys.path.insert(0, str(Path(__file__).resolve().parent))
import degenerate_inputs  # noqa: E402
from degenerate_inputs import SMALL_PLAN, STATIC_KINDS, TABLE_KINDS, Drawn  # noqa: E402

from rotcal.simulate import SimulationSpec, simulate, write_dataset  # noqa: E402


def good(rng: np.random.Generator, path: Path) -> Drawn:
    """A small-plan table dataset as ``rotcal simulate`` writes it."""
    spec, seed = SimulationSpec(plan=SMALL_PLAN), int(rng.integers(2**31))
    write_dataset(simulate(spec, seed), spec, path, "csv")
    truth = json.loads((path / "truth.json").read_text())["intrinsic"]
    return Drawn(path, "good", f"seed {seed}", np.array([truth[k] for k in degenerate_inputs._INTRINSIC]))


def wrapped(rng: np.random.Generator, path: Path) -> Drawn:
    """A static recording whose channel u sits near 2^31 in a signed
    32-bit output, wrapping around."""
    drawn = degenerate_inputs.static_recording(rng, "noise_free", path)
    csv = path / "positions.csv"
    frame = pl.read_csv(csv)
    frame.with_columns(u=(pl.col("u").round().cast(pl.Int64) + 2**32 - 100) % 2**32 - 2**31).write_csv(csv)
    return Drawn(path, "static wrapped", drawn.detail, drawn.truth)


def build(root: Path, n_good: int, seed: int) -> dict[str, Drawn]:
    drawn = {}
    for i in range(n_good):
        drawn[f"good_{i:02d}"] = good(np.random.default_rng([seed, i]), root / f"good_{i:02d}")
    kinds = [("static", k) for k in STATIC_KINDS] + [("table", k) for k in TABLE_KINDS]
    for j, (family, kind) in enumerate(kinds):
        make = degenerate_inputs.static_recording if family == "static" else degenerate_inputs.table_recording
        # the quantized ones at the coarsest step drawn (1000 counts)
        drawn[f"{family}_{kind}"] = make(np.random.default_rng([seed, 1000 + j]), kind, root / f"{family}_{kind}",
                                         1000.0 if kind == "quantized" else None)
    drawn["static_wrapped"] = wrapped(np.random.default_rng([seed, 2000]), root / "static_wrapped")
    return drawn


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--good", type=int, default=20)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds the batch may take")
    parser.add_argument("--report", type=Path, default=None)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rotcal-degenerate-batch-") as tmp:
        root, out = Path(tmp) / "root", Path(tmp) / "out"
        drawn = build(root, args.good, args.seed)
        start = time.perf_counter()
        try:
            done = subprocess.run([sys.executable, "-m", "rotcal", "batch", str(root), "--out", str(out), "--workers",
                                   str(args.workers), "--json"], capture_output=True, text=True, timeout=args.timeout)
        except subprocess.TimeoutExpired:
            print(f"no result within {args.timeout:g} s (a hang)")
            return 1
        elapsed = time.perf_counter() - start
        summary = json.loads(done.stdout)
        problems = {p["dataset_path"]: p for p in summary["problems"]}
        lines, broken = [], 0
        for name, d in drawn.items():
            if name in problems:
                problem = problems[name]
                ok = problem["status"] == "quarantined" and "\n" not in problem["reason"] and d.kind != "good"
                verdict = f"quarantined: {problem['reason']}" if ok else f"VIOLATION {problem['status']}: {problem['reason']}"
            else:
                tables = next((out / "datasets" / name).rglob("intrinsic.parquet"), None)
                violation = "not published" if tables is None else degenerate_inputs.published_violation(d.truth, tables.parent)
                ok = violation is None
                verdict = "published, within 5 u, no finding" if ok else f"VIOLATION: {violation}"
            broken += not ok
            lines.append(f"{name} ({d.kind}, {d.detail}): {verdict}")
        published = summary["ok"]
        head = (f"{len(drawn)} datasets ({args.good} good), {args.workers} workers: exit {done.returncode}, "
                f"{published} published, {summary['quarantined']} quarantined, {summary['errors']} errors; "
                f"{elapsed:.1f} s; {broken} violations")
        broken += done.returncode != 4 or summary["errors"] != 0
    text = "\n".join([head, *lines]) + "\n"
    print(text, end="")
    if args.report is not None:
        args.report.write_text(text)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
