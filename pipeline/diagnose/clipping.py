"""Runs of samples stuck at the extremes: the signature of clipping.

Without clipping, the largest value a channel takes is an extreme of the
noise and is rarely repeated; the density of values falls towards it. A
converter that saturates piles every sample beyond its limit onto one value.
The test compares the count at the extreme value with the count one output
quantum inside it: under no clipping the extreme is no more likely than its
neighbour, so a one-sided binomial test at p = 1/2 bounds the false-alarm
rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import binom

from rotcal.model.physics import CHANNELS


@dataclass(frozen=True)
class StuckValue:
    channel: str
    side: str          # "high" or "low"
    value: float
    count: int
    neighbour_count: int
    p_value: float


def quantum(y: np.ndarray) -> float:
    """The output's resolution: 1 for integer outputs, else the smallest step seen."""
    if np.all(y == np.round(y)):
        return 1.0
    steps = np.diff(np.unique(y))
    return float(steps[steps > 0].min()) if steps.size else 1.0


def stuck_values(y: np.ndarray, q: float) -> list[StuckValue]:
    """Per channel and side, the extreme value with its evidence."""
    out = []
    for r, channel in enumerate(CHANNELS):
        col = y[:, r]
        for side, value, inner in (("high", col.max(), -q), ("low", col.min(), q)):
            count = int(np.count_nonzero(col == value))
            lo, hi = sorted((value + inner, value))
            neighbour = int(np.count_nonzero((col >= lo) & (col <= hi))) - count
            p = float(binom.sf(count - 1, count + neighbour, 0.5))
            out.append(StuckValue(channel, side, float(value), count, neighbour, p))
    return out


def clip_limits(evidence: list[StuckValue], alpha: float) -> tuple[float | None, float | None]:
    """(clip_low, clip_high) where some channel is stuck beyond the false-alarm
    rate ``alpha`` (Bonferroni over channels and sides); the converter's limit
    is common to all channels, so the most-populated stuck value wins."""
    limits = []
    for side in ("low", "high"):
        hits = [e for e in evidence if e.side == side and e.p_value < alpha / len(evidence)]
        limits.append(max(hits, key=lambda e: e.count).value if hits else None)
    return limits[0], limits[1]
