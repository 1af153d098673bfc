"""A long capture simulated in bounded memory. The default
plan with long rotations (``[plan] rotation_samples``) written as an MCAP
CDR capture block by block (``simulate.blocks``, what ``rotcal simulate``
does) against the in-memory simulator (``simulate`` + ``write_dataset``) on
the same spec and seed, each in its own process: time per sample, peak
resident memory (the process's ``ru_maxrss``), and whether the files are
the same bytes. Then, on that capture read in memory, the segments and
segment fits streamed (``blockwise.segments.stream_segments`` over blocks of
``--block`` samples, two passes) against the in-memory stage
(``segment_by_labels`` + ``fit_segments``, one thread): time per sample,
the largest difference between their fits tables, and the peak of memory
each allocates beyond the sample table (``tracemalloc``).

Last, ``rotcal run`` on that capture, each in a process of its own under
``/usr/bin/time -v``: read block by block (the default, ``[run]
stream_above_samples`` 0) against read whole (the key above the capture); CPU seconds per sample
(the machine may be loaded: wall time is printed too), peak resident
memory, and the largest difference between their tables (of the column's
largest value; ``tests/test_streaming.py`` bounds them). ``--streamed-only``
(captures beyond memory) runs only the default configuration.

    python bench/streaming.py [--samples 10000000] [--dir /tmp] [--streamed-only] [--block 1048576]
"""

from __future__ import annotations

import argparse
import filecmp
import json
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

CHILD = """
import json, resource, sys
from dataclasses import replace
from pathlib import Path
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.blocks import write_streamed
spec = SimulationSpec()
spec = replace(spec, plan=replace(spec.plan, rotation_samples={rotation}))
out = Path({out!r})
if {streamed}:
    write_streamed(spec, 1, out, "bench")
else:
    write_dataset(simulate(spec, 1), spec, out, "mcap-cdr", "bench")
print(json.dumps({{"peak_kib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}}))
"""


def measure(rotation: int, out: Path, streamed: bool) -> tuple[float, float]:
    """Seconds and peak resident MB of one simulation in a process of its own."""
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-c", CHILD.format(rotation=rotation, out=str(out), streamed=streamed)],
                          check=True, capture_output=True, text=True)
    seconds = time.perf_counter() - start
    return seconds, json.loads(done.stdout.splitlines()[-1])["peak_kib"] / 1024


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=10_000_000)
    parser.add_argument("--dir", type=Path, default=Path(tempfile.gettempdir()))
    parser.add_argument("--streamed-only", action="store_true", help="skip the in-memory simulator (captures beyond memory)")
    parser.add_argument("--block", type=int, default=1 << 20, help="samples a block when the fits are streamed")
    args = parser.parse_args()
    from rotcal.simulate import Plan

    plan = Plan()
    static = len(plan.axes) * int(360 / plan.step_deg) * plan.step_samples
    rotation = max(1, (args.samples - static) // (len(plan.axes) * len(plan.rates_hz)))
    n = static + rotation * len(plan.axes) * len(plan.rates_hz)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        t_s, mb_s = measure(rotation, Path(tmp) / "streamed", True)
        size = (Path(tmp) / "streamed" / "capture.mcap").stat().st_size
        print(f"simulate, streamed ({n:,} samples, rotation_samples {rotation:,}, {size / 1e9:.2f} GB): "
              f"{n / t_s:,.0f} samples/s, peak {mb_s:,.0f} MB ({mb_s * 1e6 / n:.1f} B/sample)", flush=True)
        if args.streamed_only:
            run(Path(tmp) / "streamed", n, {"default configuration": None})
            return
        t_m, mb_m = measure(rotation, Path(tmp) / "memory", False)
        same = filecmp.cmp(Path(tmp) / "streamed" / "capture.mcap", Path(tmp) / "memory" / "capture.mcap", shallow=False)
        print(f"simulate, in memory: {n / t_m:,.0f} samples/s, peak {mb_m:,.0f} MB ({mb_m * 1e6 / n:.1f} B/sample)")
        print(f"streamed / in memory: speed {t_m / t_s:.2f}x, peak memory {mb_s / mb_m:.3f}x; same bytes: {same}")
        fits(Path(tmp) / "streamed", args.block)
        run(Path(tmp) / "streamed", n, {"streamed": 0, "in memory": n})


def run(dataset: Path, n: int, ways: dict[str, int | None]) -> None:
    """``rotcal run`` on ``dataset`` each way (``[run] stream_above_samples``;
    None: the default configuration), CPU time, wall time and peak resident
    memory from ``/usr/bin/time -v``; the tables compared when there are two."""
    import numpy as np
    import polars as pl

    rotcal = Path(sys.executable).with_name("rotcal")
    cpu, wall, outs = {}, {}, []
    for name, above in ways.items():
        out = dataset.parent / f"run-{len(outs)}"
        config = ["--config", str(dataset.parent / "stream.toml")] if above is not None else []
        if above is not None:
            (dataset.parent / "stream.toml").write_text(f"[run]\nstream_above_samples = {above}\n")
        done = subprocess.run(["/usr/bin/time", "-v", str(rotcal), "run", str(dataset), "--out", str(out), "--quiet", *config],
                              check=True, capture_output=True, text=True)
        field = dict(line.strip().rsplit(": ", 1) for line in done.stderr.splitlines() if ": " in line)
        cpu[name] = float(field["User time (seconds)"]) + float(field["System time (seconds)"])
        wall[name] = sum(float(p) * 60 ** i for i, p in enumerate(reversed(field["Elapsed (wall clock) time (h:mm:ss or m:ss)"].split(":"))))
        print(f"rotcal run, {name}: CPU {cpu[name] * 1e9 / n:,.0f} ns/sample ({cpu[name]:,.1f} s), wall {wall[name]:,.1f} s, "
              f"peak resident {int(field['Maximum resident set size (kbytes)']) / 1024:,.0f} MB", flush=True)
        outs.append(out)
    if len(outs) == 2:
        differences = []  # (difference of the column's largest value, table, column, the column's largest value)
        for table in sorted(outs[1].glob("*.parquet")):
            a, b = pl.read_parquet(outs[0] / table.name), pl.read_parquet(table)
            for c in (c for c, d in b.schema.items() if d in (pl.Float64, pl.List(pl.Float64))):
                x, y = (np.array(f[c].explode().fill_null(np.nan).to_numpy(), float) for f in (a, b))
                largest = float(np.nanmax(np.abs(y), initial=0.0))
                differences.append((float(np.nanmax(np.abs(x - y), initial=0.0) / max(largest, 1e-300)), table.stem, c, largest))
        differences.sort(reverse=True)
        first, second = ways
        print(f"rotcal run, {first} / {second}: CPU time per sample {cpu[first] / cpu[second]:.2f}x, "
              f"wall time {wall[first] / wall[second]:.2f}x (the target: at most 1.00x)")
        # a column whose values are rounding noise (an uncertainty near zero) differs by much of itself: named, so
        # the reader can tell it from a real difference; the largest of every other table follows
        worst, table, column, largest = differences[0]
        rest = max((d for d in differences if d[1] != table), default=(0.0, "-", "-", 0.0))
        print(f"  largest difference between their tables: {worst:.1e} of the column's largest value ({table}.{column}, "
              f"largest value {largest:.3g}); in any other table: {rest[0]:.1e} ({rest[1]}.{rest[2]})")


def traced(fn):
    """fn's result, seconds and peak traced allocation (MB)."""
    tracemalloc.start()
    start = time.perf_counter()
    out = fn()
    seconds = time.perf_counter() - start
    peak = tracemalloc.get_traced_memory()[1] / 1e6
    tracemalloc.stop()
    return out, seconds, peak


def fits(dataset: Path, block: int, repeats: int = 3) -> None:
    """Segments and fits, streamed against in memory, on one thread."""
    import numpy as np
    import polars as pl
    from common import best_of
    from threadpoolctl import threadpool_limits

    from rotcal.blockwise.segments import stream_segments
    from rotcal.config import FitConfig
    from rotcal.fit.segments import fit_segments, fits_frame
    from rotcal.ingest.dataset import load_dataset
    from rotcal.segment import segment_by_labels

    ds = load_dataset(dataset)
    samples, config, n = ds.samples, FitConfig(), ds.samples.height

    def in_memory():
        labelled, segments = segment_by_labels(samples, ds.name, ds.meta.angle_source)
        return fits_frame(fit_segments(labelled, segments.filter(pl.col("angle_source") != "none"), config, 1), segments, ds.name)

    def streamed():
        def blocks():
            return (samples.slice(a, block) for a in range(0, n, block))
        result = stream_segments(blocks, ds.name, ds.meta.angle_source, config, 100_000)
        return fits_frame(result.fits, result.segments, ds.name)

    with threadpool_limits(limits=1):  # as run_dataset holds BLAS
        ours, _, mb_s = traced(streamed)
        theirs, _, mb_m = traced(in_memory)
        t_s, t_m = best_of(streamed, repeats), best_of(in_memory, repeats)
    # each column's largest difference against its largest value (entries zero but for rounding stay comparable)
    worst = max(float(np.nanmax(np.abs(ours[c].to_numpy() - theirs[c].to_numpy())) / np.nanmax(np.abs(theirs[c].to_numpy())))
                for c in ("C", "A", "B", "u_C", "u_A", "u_B", "sigma", "rms", "max_abs_residual", "lag1_autocorr"))
    print(f"segments + fits, streamed (blocks of {block:,}): {n / t_s:,.0f} samples/s, peak allocated {mb_s:,.0f} MB")
    print(f"segments + fits, in memory: {n / t_m:,.0f} samples/s, peak allocated {mb_m:,.0f} MB (beside the sample table)")
    print(f"streamed / in memory: speed {t_m / t_s:.2f}x (best of {repeats}); "
          f"largest difference in the fits table {worst:.1e} of the column's largest value")

if __name__ == "__main__":
    main()
