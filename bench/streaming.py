"""Issue 16 item 1: a long capture simulated in bounded memory. The default
plan with long rotations (``[plan] rotation_samples``) written as an MCAP
CDR capture block by block (``simulate.streamed``, what ``rotcal simulate``
does) against the in-memory simulator (``simulate`` + ``write_dataset``) on
the same spec and seed, each in its own process: time per sample, peak
resident memory (the process's ``ru_maxrss``), and whether the files are
the same bytes.

    python bench/streaming.py [--samples 10000000] [--dir /tmp] [--streamed-only]
"""

from __future__ import annotations

import argparse
import filecmp
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = """
import json, resource, sys
from dataclasses import replace
from pathlib import Path
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.streamed import write_streamed
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
            return
        t_m, mb_m = measure(rotation, Path(tmp) / "memory", False)
        same = filecmp.cmp(Path(tmp) / "streamed" / "capture.mcap", Path(tmp) / "memory" / "capture.mcap", shallow=False)
        print(f"simulate, in memory: {n / t_m:,.0f} samples/s, peak {mb_m:,.0f} MB ({mb_m * 1e6 / n:.1f} B/sample)")
        print(f"streamed / in memory: speed {t_m / t_s:.2f}x, peak memory {mb_s / mb_m:.3f}x; same bytes: {same}")


if __name__ == "__main__":
    main()
