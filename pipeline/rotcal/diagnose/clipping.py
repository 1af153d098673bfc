"""Runs of samples stuck at the extremes: the signature of clipping.

Without clipping, the largest value a channel takes is an extreme of the
noise and is rarely repeated; the density of values falls towards it. A
converter that saturates piles every sample beyond its limit onto one value.
Two tests, the smaller p-value doubled (Bonferroni):

- the count at the extreme value against the count one output quantum
  inside it: under no clipping the extreme is no more likely than its
  neighbour, so a one-sided binomial test at p = 1/2 bounds the false-alarm
  rate. It needs no model, so it runs before the model is selected.
- the censoring test, given a model's predictions mu and noise sigma: of
  the samples that reach the extreme's bin (x >= c - q/2), none went beyond
  it, an event of probability prod pi_i without clipping, pi_i = 1 -
  P(x_i >= c + q/2) / P(x_i >= c - q/2), x_i ~ N(mu_i, sigma^2); that product
  is its p-value (for a given c, P(reject) = P(event and prod <= t) <= t;
  taking c at the extreme only lowers the rate). Clipped samples that sit
  well above the model's noise weigh more than a pile counted against its
  neighbour: on the default plan it needs about a quarter as many clipped
  samples (docs/power.md). It is only as valid as mu and sigma: an
  overestimated sigma (a model that misfits, 60 bits of residual where the
  sensor has 8) makes every sample near the top look censored. So it runs on
  the selected model, and sigma is the smaller of the model's and the
  local scatter of successive residuals (``successive_noise``), which a
  misfit that varies slowly from sample to sample does not inflate; a
  smaller sigma only makes the test more conservative. Since c is the
  extreme itself, its own sample always sits in c's bin: the test is valid
  only on a grid coarse against the noise (``COARSE``; on the default plan
  the quantum is an eighth of the noise), and is not made on a finer one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import betainc, log_ndtr

from rotcal.fit.quantization import output_step
from rotcal.model.physics import CHANNELS

# The censoring test only where the quantum is at least this fraction of the
# noise: the extreme defines c, so its own sample is always in c's bin, with
# pi about z q / sigma (z about 4 at the extreme of 1e5 samples); on a fine
# grid (float outputs, noise-free data) that alone would look censored.
COARSE = 0.05


@dataclass(frozen=True)
class StuckValue:
    channel: str
    side: str          # "high" or "low"
    value: float
    count: int
    neighbour_count: int
    p_value: float     # the two tests' smaller p-value, doubled (the binomial's alone, doubled, without a model)


def quantum(y: np.ndarray) -> float:
    """The output's resolution: the coarsest channel's output step
    (``fit.quantization``: 1 for integer outputs, 100 where a logger keeps
    the top bits), else the smallest step seen."""
    found = output_step(y.reshape(len(y), -1))
    if np.any(found > 0):
        return float(found.max())
    steps = np.diff(np.unique(y))
    return float(steps[steps > 0].min()) if np.any(steps > 0) else 1.0


def censoring_gain(mu: np.ndarray, sigma: np.ndarray, limit: np.ndarray | float, q: float) -> np.ndarray:
    """Per sample at an upper ``limit``, -ln pi = ln P(x >= limit - q/2) - ln
    P(x in limit's bin), x ~ N(mu, sigma^2): what censoring at the limit
    gains over the quantized sample, computed in the tail (log_ndtr)."""
    lower = (limit - q / 2 - mu) / sigma
    upper = lower + q / sigma
    return -np.log1p(-np.exp(log_ndtr(-upper) - log_ndtr(-lower)))


def successive_noise(resid: np.ndarray, run: np.ndarray) -> np.ndarray:
    """Per channel, the noise standard deviation from the differences of
    successive residuals within a ``run`` (the von Neumann estimate,
    E (e_i+1 - e_i)^2 = 2 sigma^2 for white noise): a misfit that changes
    little between samples cancels in the differences."""
    same = run[1:] == run[:-1]
    step = np.diff(resid, axis=0)[same]
    return np.sqrt(np.mean(step**2, axis=0) / 2)


def stuck_values(y: np.ndarray, q: float, model: tuple[np.ndarray, np.ndarray] | None = None) -> list[StuckValue]:
    """Per channel and side, the extreme value with its evidence; ``model``:
    the predictions (n, 3) and noise (3,) or (n, 3) for the censoring test."""
    out = []
    noise = None if model is None else np.broadcast_to(model[1], y.shape)
    for r, channel in enumerate(CHANNELS):
        col = y[:, r]
        for side, value, inner in (("high", col.max(), -q), ("low", col.min(), q)):
            at = col == value
            count = int(np.count_nonzero(at))
            lo, hi = sorted((value + inner, value))
            neighbour = int(np.count_nonzero((col >= lo) & (col <= hi))) - count
            p = float(betainc(count, neighbour + 1, 0.5))  # binom.sf(count - 1, count + neighbour, 1/2), the same bits
            if model is not None and noise is not None and q >= COARSE * noise[at, r].max():
                sign = 1.0 if side == "high" else -1.0   # the low side mirrored
                p = min(p, float(np.exp(-censoring_gain(sign * model[0][at, r], noise[at, r], sign * value, q).sum())))
            out.append(StuckValue(channel, side, float(value), count, neighbour, min(1.0, 2 * p)))
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
