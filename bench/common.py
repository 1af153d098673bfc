"""Shared by the benchmark scripts: best-of-N timing (the machine may be
shared; the fastest of N runs is the least disturbed) and one report line
per measurement, as a ratio against a reference measured in the same run."""

from __future__ import annotations

import time
from collections.abc import Callable


def best_of(fn: Callable[[], object], repeats: int) -> float:
    """Wall-clock seconds of the fastest of ``repeats`` calls (after one warm-up)."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def report(what: str, count: int, unit: str, seconds: float, reference: str, ref_seconds: float) -> float:
    """Print rotcal's and the reference's rates and their ratio; return the ratio."""
    ours, theirs = count / seconds, count / ref_seconds
    ratio = ours / theirs
    print(f"{what}: {ours:,.0f} {unit}/s; {reference}: {theirs:,.0f} {unit}/s; ratio {ratio:.2f}x", flush=True)
    return ratio


def best_cpu_of(fn: Callable[[], object], repeats: int) -> float:
    """CPU seconds (all threads of the process) of the least of ``repeats``
    calls, after one warm-up: on a loaded machine the wall clock counts the
    other jobs' time too, the CPU time only this one's."""
    fn()
    times = []
    for _ in range(repeats):
        start = time.process_time()
        fn()
        times.append(time.process_time() - start)
    return min(times)
