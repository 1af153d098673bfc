"""Issue 16 item 1: a capture read chunk by chunk (``ingest.formats.blocks``) against
the in-memory reader on the same MCAP capture, each in its own process:

- in memory: ``load_dataset`` + ``repair_timebase`` (the samples table whole);
- streamed: ``open_stream`` (a first pass over the chunks keeping the
  stamps on disk, the time base from passes over them) and one pass of
  ``blocks()`` (the DUT and table channels followed side by side).

Each child reports its CPU time (``time.process_time``: the machine is
shared, wall times are printed beside them), samples per CPU second, and
its peak resident memory beyond what it held after its imports (VmHWM,
reset through /proc/self/clear_refs). With ``--check`` the streamed blocks
are compared with the in-memory samples (bit for bit) in a third process.
A capture is simulated block by block when ``--dir`` has none.

    python bench/stream_source.py [--rotation-samples 400000] [--dir /tmp/stream-source] [--block 1048576] [--check]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

CHILD = """
import json, sys, time
from pathlib import Path
import polars as pl
from rotcal.ingest.dataset import load_dataset
from rotcal.ingest.meta import load_meta
from rotcal.ingest.formats.blocks import COLUMNS, open_stream
from rotcal.timebase import repair_timebase
from rotcal.blockwise.repaired import repaired_stream

def peak_kb():
    return int(next(l for l in open("/proc/self/status") if l.startswith("VmHWM")).split()[1])

def rss_kb():
    return int(next(l for l in open("/proc/self/status") if l.startswith("VmRSS")).split()[1])

directory, part, block = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
open("/proc/self/clear_refs", "w").write("5")  # VmHWM from here
base = rss_kb()
cpu, wall = time.process_time(), time.perf_counter()
result = {}
if part == "memory":
    ds = load_dataset(directory)
    tb = repair_timebase(ds.samples, ds.name)
    result["samples"] = tb.samples.height
elif part == "stream":
    meta = load_meta(directory / "dataset.toml")
    capture = repaired_stream(open_stream(directory / "capture.mcap", meta, block_samples=block), block_samples=block)
    result["open_cpu_s"] = time.process_time() - cpu
    result["samples"] = sum(b.height for b in capture.blocks())
    result["bounded"] = capture.bounded
    result["pass_cpu_s"] = time.process_time() - cpu - result["open_cpu_s"]
else:
    ds = load_dataset(directory)
    memory = repair_timebase(ds.samples, ds.name).samples.select(COLUMNS)
    capture = repaired_stream(open_stream(directory / "capture.mcap", ds.meta, block_samples=block), block_samples=block)
    offset, equal = 0, True
    for b in capture.blocks():
        equal &= b.equals(memory.slice(offset, b.height))
        offset += b.height
    result["equal"] = bool(equal and offset == memory.height)
result.update(cpu_s=time.process_time() - cpu, wall_s=time.perf_counter() - wall,
              peak_growth_mb=(peak_kb() - base) / 1024)
print(json.dumps(result))
"""


def child(directory: Path, part: str, block: int) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(directory), part, str(block)], capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rotation-samples", type=int, default=400_000)
    parser.add_argument("--dir", type=Path, default=Path("/tmp/stream-source"))
    parser.add_argument("--block", type=int, default=1 << 20)
    parser.add_argument("--check", action="store_true")
    args = parser.parse_args()
    if not (args.dir / "capture.mcap").exists():
        from dataclasses import replace

        from rotcal.simulate import SimulationSpec
        from rotcal.simulate.blocks import write_streamed

        spec = SimulationSpec()
        write_streamed(replace(spec, plan=replace(spec.plan, rotation_samples=args.rotation_samples)), 5, args.dir, "dut")
    memory = child(args.dir, "memory", args.block)
    streamed = child(args.dir, "stream", args.block)
    n = memory["samples"]
    print(f"capture: {n} samples, {(args.dir / 'capture.mcap').stat().st_size / 1e6:.0f} MB; blocks of {args.block}")
    for name, r in (("in memory (load_dataset + repair_timebase)", memory), ("streamed (open_stream + one pass)", streamed)):
        print(f"{name}: {r['cpu_s']:.2f} s CPU ({n / r['cpu_s'] / 1e6:.2f} M samples/s), {r['wall_s']:.2f} s wall, "
              f"peak memory +{r['peak_growth_mb']:.0f} MB")
    print(f"streamed: open {streamed['open_cpu_s']:.2f} s CPU (first pass and time base), "
          f"a pass of blocks {streamed['pass_cpu_s']:.2f} s CPU ({n / streamed['pass_cpu_s'] / 1e6:.2f} M samples/s); "
          f"bounded {streamed['bounded']}")
    print(f"ratios streamed / in memory: CPU {streamed['cpu_s'] / memory['cpu_s']:.2f}, "
          f"peak memory {streamed['peak_growth_mb'] / memory['peak_growth_mb']:.3f}")
    if args.check:
        print(f"blocks equal to the in-memory samples: {child(args.dir, 'check', args.block)['equal']}")


if __name__ == "__main__":
    main()
