"""Why a segment cannot be fitted against the table angle: no angle
reference, too few samples, static angles or arc, or a channel stuck at one
value (``refusal``; ``refusal_from`` and the arc's bounds for a segment read
block by block, ``rotcal.blockwise``)."""

from __future__ import annotations

import numpy as np

from rotcal.config import FitConfig
from rotcal.model.physics import CHANNELS


def refusal(kind: str, angle_source: str, theta_deg: np.ndarray, config: FitConfig) -> str | None:
    """Why a segment cannot be fitted against the table angle, or None."""
    n = theta_deg.size
    if angle_source == "none" or n < config.min_samples:
        return refusal_from(kind, angle_source, n, 0, 0.0, config)
    steps = np.unique(theta_deg).size if kind == "static" else 0  # a sort: only where the step count matters
    return refusal_from(kind, angle_source, n, steps, arc_deg(theta_deg), config)


def refusal_from(kind: str, angle_source: str, n: int, steps: int, span: float, config: FitConfig) -> str | None:
    """``refusal`` from a segment's sample count, distinct static angles and arc (``arc_deg``)."""
    if angle_source == "none":
        if kind == "rotation":
            return ("no angle reference: a rotation segment without angle_deg or a table channel "
                    "cannot be fitted against the table angle (reduce it as an unlabelled recording)")
        return "static steps without angle_deg"
    if n < config.min_samples:
        return f"too short: {n} samples (at least {config.min_samples} needed)"
    if kind == "static" and steps < 3:
        return f"only {steps} static angle{'s' if steps != 1 else ''} (at least 3 needed)"
    if span < config.min_span_deg:
        return f"angle range {span:.1f} deg is below the {config.min_span_deg:g} deg needed to separate offset and sine terms"
    return None


def arc_deg(theta_deg: np.ndarray) -> float:
    """The arc the angles cover on the circle, not their unwrapped range: a
    rotation sampled at a multiple of its rate (aliased) repeats one angle,
    however many turns it makes. The smaller of the ranges of theta mod 360
    and of (theta + 180) mod 360, so an arc across 0 deg is measured whole."""
    low, high = arc_bounds(theta_deg)
    return arc_from(low, high)


def arc_from(low: np.ndarray, high: np.ndarray) -> float:
    """The arc from the bounds of ``arc_bounds`` (of one block, or the
    smallest lows and largest highs of several)."""
    return float(min(high[0] - low[0], high[1] - low[1]))


def arc_bounds(theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest of theta mod 360 and of (theta + 180) mod
    360, computed in place (one scratch array; ``np.mod`` takes eight times
    as long on the long rotations); bounds are additive across blocks."""
    r = theta_deg / 360.0
    np.floor(r, out=r)
    r *= -360.0
    r += theta_deg  # theta mod 360 (the division is exact at whole turns)
    first = (float(r.min()), float(r.max()))
    r -= 180.0
    r[r < 0.0] += 360.0  # (theta + 180) mod 360
    return np.array([first[0], float(r.min())]), np.array([first[1], float(r.max())])


def stuck_from(low: np.ndarray, high: np.ndarray) -> str | None:
    """Why a segment's samples cannot be fitted, from each channel's
    smallest and largest value: a channel that holds one value throughout
    (pinned at full scale, or dead) has no residual scatter, so its fit
    would claim zero uncertainty and outweigh every other segment in the
    combination."""
    for channel, lo, hi in zip(CHANNELS, low, high):
        if lo == hi:
            return f"channel {channel} holds {lo:g} in every sample (stuck or saturated): nothing to fit"
    return None
