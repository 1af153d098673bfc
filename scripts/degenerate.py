"""The long run of the degenerate-recording property (docs/fuzzing.md,
"Degenerate recordings"): ``--inputs`` recordings drawn by
``degenerate_inputs.draw`` from ``numpy.random.default_rng([seed, i])``,
each run in a worker process with a time budget; a line per violation
(and per kind, the counts) in the report.

    python scripts/degenerate.py --inputs 2000 --seed 1 --workers 2 --report degenerate.txt

Exit status 0 when no recording broke the invariant, 1 otherwise. A
recording past its ``--timeout`` counts as a hang (its worker pool is
replaced). ``--only i`` replays one recording in this process.
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def one(seed: int, i: int) -> tuple[int, str, str, str | None, float]:
    """Recording ``i`` of ``seed``: (i, kind, detail, violation or None, seconds)."""
    import warnings

    import degenerate_inputs

    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="rotcal-degenerate-") as tmp, warnings.catch_warnings():
        warnings.simplefilter("error")  # a library warning reaching the caller is a violation too
        try:
            drawn = degenerate_inputs.draw(np.random.default_rng([seed, i]), Path(tmp) / "ds")
        except Exception as exc:  # noqa: BLE001  (drawing failed: reported, not a rotcal violation)
            return i, "draw", repr(exc), None, time.perf_counter() - start
        try:
            broken = degenerate_inputs.violation(drawn, Path(tmp) / "out")
        except Warning as warning:
            broken = f"a warning reached the caller: {warning!r}"
    return i, drawn.kind, drawn.detail, broken, time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--inputs", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--timeout", type=float, default=300.0, help="seconds a recording may take")
    parser.add_argument("--report", type=Path, default=None)
    parser.add_argument("--only", type=int, default=None)
    args = parser.parse_args()
    if args.only is not None:
        print(one(args.seed, args.only))
        return 0
    lines, kinds, broken, todo = [], Counter(), Counter(), list(range(args.inputs))
    start = time.perf_counter()
    context = multiprocessing.get_context("spawn")
    while todo:
        pool = context.Pool(args.workers, maxtasksperchild=50)
        pending = {i: pool.apply_async(one, (args.seed, i)) for i in todo}
        todo = []
        for i, result in pending.items():
            try:
                _, kind, detail, violation, seconds = result.get(timeout=args.timeout)
            except multiprocessing.TimeoutError:
                kind, detail, violation = "?", "", f"no result within {args.timeout:g} s (a hang)"
                todo = [k for k in pending if k > i]  # the rest, on a fresh pool
                lines.append(f"{i}: {violation}")
                broken["?"] += 1
                pool.terminate()
                break
            except Exception as exc:  # noqa: BLE001  (the worker itself failed: a violation, and the run goes on)
                kind, detail, violation = "?", "", f"the worker failed: {type(exc).__name__}: {exc}"
                kinds[kind] += 1
                broken[kind] += 1
                lines.append(f"{i}: {violation}")
                continue
            kinds[kind] += 1
            if violation is not None:
                broken[kind] += 1
                lines.append(f"{i} ({kind}, {detail}): {violation}")
        else:
            pool.close()
        pool.join()
    elapsed = time.perf_counter() - start
    summary = [f"{args.inputs} recordings, seed {args.seed}, {args.workers} workers: {elapsed:.0f} s, "
               f"{sum(broken.values())} violations"]
    summary += [f"  {kind}: {kinds[kind]} recordings, {broken[kind]} violations" for kind in sorted(kinds)]
    text = "\n".join(summary + lines) + "\n"
    print(text, end="")
    if args.report is not None:
        args.report.write_text(text)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
