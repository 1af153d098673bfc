"""Where one read of the MCAP JSON capture of ``bench/mcap_ingest.py`` spends
its CPU (issue 16, item 2): the least of ``--repeats`` reads, in CPU ms per
read and minor page faults, for the whole ingest and each step (chunk
decompression, ``json_lines``, the parse, the frame's checks and columns,
the table's labels), and the wall time. Steps nest (``read_topics`` holds
the decompression, the cut and the parse; ``_capture`` the rest).

Run with ``--workers 1`` and ``POLARS_MAX_THREADS=1`` for the CPU of each
step on one core (polars' threads then run only while the caller waits,
so the caller's step holds their time); on more cores the step times hold
only the calling thread's share. Another rotcal's source tree can be
measured by putting it first on ``PYTHONPATH`` (a directory with
``rotcal`` linked to its ``pipeline``): alternate the two, on a shared
machine the least of several runs is the figure.

    POLARS_MAX_THREADS=1 python bench/json_profile.py --workers 1 [--repeats 9]
"""

from __future__ import annotations

import argparse
import resource
import tempfile
import time
from pathlib import Path

import rotcal
from rotcal.config import Limits
from rotcal.ingest.formats.mcap import columns as mcap_columns
from rotcal.ingest.formats.mcap import fast as mcap_fast
from rotcal.ingest.formats.mcap import reader as mcap_source
from rotcal.ingest.meta import load_meta
from rotcal.simulate import Plan, SimulationSpec, simulate, write_mcap

STEPS = ((mcap_fast, "read_topics"), (mcap_fast, "chunk_data"), (mcap_columns, "json_lines"),
         (mcap_columns, "parse_json_lines"), (mcap_source, "_capture"), (mcap_source, "_json_frame"),
         (mcap_source, "table_labels"), (mcap_source, "fast_table_track"), (mcap_source, "label_columns"))


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def instrument(totals: dict[str, list[float]]) -> None:
    """Wrap each step of ``STEPS`` (a module's global: its callers look it up
    at each call) to add its CPU seconds and page faults to ``totals``."""
    for module, name in STEPS:
        fn = getattr(module, name)

        def timed(*args, _fn=fn, _name=name, **kwargs):
            cpu, faults = time.process_time(), _faults()
            try:
                return _fn(*args, **kwargs)
            finally:
                step = totals.setdefault(_name, [0.0, 0.0])
                step[0] += time.process_time() - cpu
                step[1] += _faults() - faults
        setattr(module, name, timed)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rotation-samples", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=9)
    parser.add_argument("--workers", type=int, default=0, help="cores the read may use (0: all)")
    args = parser.parse_args()
    sim = simulate(SimulationSpec(plan=Plan(rotation_samples=args.rotation_samples)), 1)
    meta = load_meta(None)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_mcap(sim, Path(tmp) / "json.mcap", encoding="json")
        read = lambda: mcap_source.read_mcap_capture(path, meta, None, Limits(), args.workers)  # noqa: E731
        read()
        runs = []
        for _ in range(args.repeats):  # the whole read, uninstrumented
            wall, cpu, faults = time.perf_counter(), time.process_time(), _faults()
            read()
            runs.append((time.process_time() - cpu, time.perf_counter() - wall, _faults() - faults))
        totals: dict[str, list[float]] = {}
        instrument(totals)
        steps = []
        for _ in range(args.repeats):
            totals.clear()
            read()
            steps.append({name: tuple(v) for name, v in totals.items()})
    cpu, wall, faults = min(runs)
    print(f"rotcal at {Path(rotcal.__file__).parent}: {sim.samples.height:,} messages, workers {args.workers}")
    print(f"read_mcap_capture: CPU {cpu * 1e3:.1f} ms (least of {args.repeats}), wall {min(r[1] for r in runs) * 1e3:.1f} ms, "
          f"{faults:,} page faults")
    for name in steps[0]:
        least = min(s[name] for s in steps if name in s)
        print(f"  {name:18s} CPU {least[0] * 1e3:6.1f} ms  {least[1]:7,.0f} page faults")


if __name__ == "__main__":
    main()
