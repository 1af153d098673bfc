"""How many cores rotcal may use: the one rule that the fit stage's threads,
the MCAP reader's decompression threads and the batch pool all read.

``workers`` (``[run] workers``, ``rotcal batch --workers``) counts cores in
all: N > 0 means N, 0 means every core this process may run on (its CPU
affinity: ``taskset``, a container's cpuset, a scheduler's allocation, not
the machine's count). A batch of W jobs side by side gives each dataset
run its share of the batch's cores, ``share``: one core each when W fills
them.
"""

from __future__ import annotations

import os


def available_cores() -> int:
    """The cores this process may run on (at least 1)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def cores(workers: int = 0) -> int:
    """The cores a stage may keep busy: ``workers`` if given (> 0), else
    every available core."""
    return workers if workers > 0 else available_cores()


def share(workers: int, parts: int) -> int:
    """Each of ``parts`` side-by-side jobs' cores out of ``cores(workers)``."""
    return max(1, cores(workers) // max(parts, 1))
