"""The diagnosis's CPU cost per dataset, by stage and by function, on
default-plan datasets clean and with a catalogue effect (the mix of
bench/batch_e2e.py: two thirds carry one effect, sizes across its range).

Each dataset is read, segmented, fitted and reduced once (not timed); then
``run.recommended.diagnose_stage`` and ``recommended_fits`` (the refined model's
segment fits) are timed with ``time.process_time`` (CPU, so a shared machine
disturbs it little), under cProfile when ``--profile`` is given (its
overhead inflates the totals; the per-function shares, CPU seconds as well, are what it is for).
``--reference DIR`` runs the same measurement with another rotcal source
tree (DIR/pipeline/rotcal, DIR/schemas, DIR/configs: e.g. ``git archive main``
unpacked) in a subprocess of the same interpreter, alternating with this
tree dataset kind by kind, and prints the ratio, with both outputs' diagnosis
tables compared.

    python bench/diagnosis_profile.py [--datasets 15] [--reference DIR] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from batch_e2e import _simulate  # noqa: E402  (the same datasets as the batch bench)

KINDS = ("clean", "mix")


def measure(root: Path, profile: bool) -> dict:
    """CPU seconds of the diagnosis and of the refined fits per dataset of
    ``root``, with each diagnosis's findings (to compare trees) and the
    cProfile statistics (cumulative seconds per function) when asked."""
    from threadpoolctl import threadpool_limits

    from rotcal.config import RunConfig
    from rotcal.ingest.dataset import load_dataset
    from rotcal.run import Reductions, determined, diagnose_stage, intrinsic_table, recommend_stage, recommended_fits
    from rotcal.run.stages import reduce, segment_and_fit

    config = RunConfig()
    profiler = cProfile.Profile(time.process_time) if profile else None  # CPU, as the totals
    diagnosis_cpu, refined_cpu, findings = [], [], []
    with threadpool_limits(limits=1, user_api="blas"):
        for k, path in enumerate([*sorted(root.iterdir())[:1], *sorted(root.iterdir())]):  # the first twice: warm-up
            ds = load_dataset(path, None, config.limits, 1)
            seg = segment_and_fit(ds, config)
            reductions = reduce(seg, ds)
            results, frames, _ = determined(reductions, seg, path)
            assert isinstance(reductions, Reductions)
            if profiler and k:
                profiler.enable()
            start = time.process_time()
            diagnosis, notes = diagnose_stage(seg, reductions, results, ds, config)
            middle = time.process_time()
            chosen = recommend_stage(intrinsic_table(results, diagnosis, ds, None), results, frames, diagnosis,
                                     reductions, config, notes)
            fits = recommended_fits(seg, diagnosis, chosen, ds, config)
            end = time.process_time()
            if profiler and k:
                profiler.disable()
            if k:
                diagnosis_cpu.append(middle - start)
                refined_cpu.append(end - middle)
                findings.append(diagnosis.findings.write_json() + diagnosis.parameters.write_json()
                                + json.dumps([r.state.tolist() + r.state_cov.ravel().tolist() for r in diagnosis.refined])
                                + fits.write_json())
    out: dict = {"diagnosis": diagnosis_cpu, "refined": refined_cpu, "findings": findings}
    if profiler:
        stats = pstats.Stats(profiler)
        out["functions"] = {f"{Path(f).name}:{name}": (tt, ct, nc) for (f, _, name), (_, nc, tt, ct, _) in
                            stats.stats.items()}  # type: ignore[attr-defined]
    return out


def _tree_env(tree: Path, scratch: Path) -> dict[str, str]:
    """An environment whose ``import rotcal`` is ``tree``'s source (PYTHONPATH
    precedes the editable install's finder)."""
    scratch.mkdir(parents=True, exist_ok=True)
    package = tree / "pipeline" / "rotcal"
    package = package if package.is_dir() else tree / "pipeline"  # trees before the src-style layout
    for name, source in (("rotcal", package), ("rotcal_schemas", tree / "schemas"), ("rotcal_configs", tree / "configs")):
        link = scratch / name
        if not link.exists():
            link.symlink_to(source)
    return {**os.environ, "PYTHONPATH": str(scratch)}


def run_tree(root: Path, profile: bool, env: dict[str, str] | None) -> dict:
    """``measure`` in a fresh process of this interpreter (``env``: another tree)."""
    run = subprocess.run([sys.executable, __file__, "--measure", str(root)] + (["--profile"] if profile else []),
                         capture_output=True, text=True, env=env)
    if run.returncode:
        raise SystemExit(run.stderr[-3000:])
    return json.loads(run.stdout)


def _summary(who: str, kind: str, m: dict) -> tuple[float, float]:
    d, r = np.mean(m["diagnosis"]), np.mean(m["refined"])
    print(f"{who}, {kind}, {len(m['diagnosis'])} datasets: diagnose_stage {1e3 * d:.0f} ms CPU a dataset "
          f"(min {1e3 * min(m['diagnosis']):.0f}, max {1e3 * max(m['diagnosis']):.0f}), recommended_fits "
          f"{1e3 * r:.1f} ms", flush=True)
    return float(d), float(r)


def _top(m: dict, n: int = 25) -> None:
    per = len(m["diagnosis"])
    rows = sorted(m["functions"].items(), key=lambda kv: -kv[1][1])[:n]
    for name, (tt, ct, calls) in rows:
        print(f"    {1e3 * ct / per:8.1f} ms cum {1e3 * tt / per:8.1f} ms own {calls / per:8.1f} calls  {name}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--datasets", type=int, default=15)
    parser.add_argument("--reference", type=Path, help="another rotcal source tree, measured beside this one")
    parser.add_argument("--profile", action="store_true", help="cProfile: the 25 costliest functions (cumulative)")
    parser.add_argument("--dir", type=Path, help="keep the simulated datasets here (reused when present)")
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.measure:
        json.dump(measure(args.measure, args.profile), sys.stdout)
        return
    with tempfile.TemporaryDirectory() as tmp:
        base = args.dir or Path(tmp)
        roots = {kind: base / kind for kind in KINDS}
        jobs = [(seed, roots[kind] / f"dut{seed:03d}", kind == "mix") for kind in KINDS
                for seed in range(1, args.datasets + 1) if not (roots[kind] / f"dut{seed:03d}").exists()]
        with ProcessPoolExecutor(2) as pool:
            list(pool.map(_simulate, jobs))
        print(f"{args.datasets} default-plan CSV datasets per kind; load average {os.getloadavg()[0]:.1f}", flush=True)
        env = _tree_env(args.reference.resolve(), Path(tmp) / "reference") if args.reference else None
        for kind in KINDS:
            this = run_tree(roots[kind], args.profile, None)
            d, r = _summary("this tree", kind, this)
            if args.profile:
                _top(this)
            if env is None:
                continue
            ref = run_tree(roots[kind], args.profile, env)
            d_ref, r_ref = _summary("reference", kind, ref)
            if args.profile:
                _top(ref)
            same = sum(a == b for a, b in zip(this["findings"], ref["findings"]))
            print(f"  {kind}: reference over this tree {d_ref / d:.2f}x (diagnosis), {r_ref / r:.2f}x (refined fits); "
                  f"findings, parameters, refined results and fits identical in {same} of {len(ref['findings'])}; "
                  f"load average {os.getloadavg()[0]:.1f}", flush=True)


if __name__ == "__main__":
    main()
