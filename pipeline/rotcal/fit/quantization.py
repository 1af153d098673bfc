"""The output step of a quantized channel, found from its samples, and what
the rounding adds to the variance of a mean.

A converter's output moves in steps Delta (one count, or a hundred where a
logger keeps the top bits). When the noise before rounding is well above
a step, the rounding is a small independent error per sample (variance
Delta^2 / 12, already in the samples' scatter); when it is below, the
samples of a pose are identical or nearly so and the rounding error is one
and the same for all of them: their mean is uncertain by the step itself,
however many there are (Widrow and Kollar, Quantization Noise, 2008,
ch. 4-5: for Gaussian noise of standard deviation sigma the mean's
rounding error falls as exp(-2 pi^2 sigma^2 / Delta^2)).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import polars as pl

from rotcal.model.columns import columns_of
from rotcal.model.physics import CHANNELS

# a channel's levels are taken from at most this many samples (evenly spread): enough to see every level
MAX_LEVEL_SAMPLES = 1_000_000
# the divisors of the smallest gap tried as the step of non-integer levels (a few levels seen: the
# smallest gap may be several steps)
MAX_DIVISOR = 10
# levels a whole number of steps apart within this fraction of a step (the float rounding of counts times a scale)
_WHOLE = 1e-3


def output_step(y: np.ndarray | Sequence[np.ndarray]) -> np.ndarray:
    """Each column's output step: the greatest step of which every gap
    between the distinct values seen is a whole multiple (integer outputs:
    the gaps' greatest common divisor, 1 with one level; other values: the
    smallest gap divided by 1 to ``MAX_DIVISOR``, the first that divides
    every gap); 0 where the values show no step (continuous outputs, or
    one level that is not an integer)."""
    columns = columns_of(y)  # (n, k), (n,) or k columns
    steps = np.zeros(len(columns))
    stride = max(1, len(columns[0]) // MAX_LEVEL_SAMPLES)
    for r, whole in enumerate(columns):
        column = whole[::stride]
        levels = np.unique(column[np.isfinite(column)])
        gaps = np.diff(levels)
        if levels.size and np.all(levels == np.round(levels)) and np.abs(levels).max() < 2.0**53:
            steps[r] = float(np.gcd.reduce(gaps.astype(np.int64))) if gaps.size else 1.0
            continue
        for divisor in range(1, MAX_DIVISOR + 1) if gaps.size else ():
            ratio = gaps / (gaps.min() / divisor)
            if np.all(np.abs(ratio - np.round(ratio)) <= _WHOLE):
                steps[r] = gaps.min() / divisor
                break
    return steps


def mean_rounding_variance(step: np.ndarray, sample_var: np.ndarray) -> np.ndarray:
    """The rounding's variance in a mean of samples of a channel of output
    ``step`` whose samples scatter with ``sample_var`` (broadcast):
    Delta^2 / 12 when the noise before rounding is nil, falling as
    exp(-4 pi^2 sigma^2 / Delta^2), sigma^2 = sample_var - Delta^2 / 12
    (Sheppard's correction) where positive. Zero where no step is known."""
    step = np.asarray(step, float)
    with np.errstate(divide="ignore", invalid="ignore"):
        sigma2 = np.maximum(sample_var - step**2 / 12.0, 0.0)
        decay = np.where(step > 0, np.exp(-4.0 * np.pi**2 * sigma2 / np.where(step > 0, step, 1.0) ** 2), 0.0)
    return step**2 / 12.0 * decay


def coarse_steps(samples: pl.DataFrame, fits: pl.DataFrame, unit: str) -> str | None:
    """Why a model-mismatch diagnosis cannot read a table recording's
    outputs, or None: a channel whose output step exceeds twice its noise
    before rounding (from the ok fits' median residual standard deviation,
    which holds the rounding's Delta^2 / 12 besides the noise). Its
    rounding error then follows the signal: a diagnosis would read its
    pattern as effects (a centripetal radius, a delay, clipping)."""
    ok = fits.filter(pl.col("status") == "ok")
    sigma = np.array([ok.filter(pl.col("channel") == c)["sigma"].median() or 0.0 for c in CHANNELS], float)
    step = output_step(samples.select(CHANNELS).to_numpy())
    noise = np.sqrt(np.maximum(sigma**2 - step**2 / 12.0, 0.0))
    coarse = np.flatnonzero((step > 0) & (noise < step / 2))
    if coarse.size == 0:
        return None
    r = int(coarse[0])
    return (f"diagnosis not run: channel {CHANNELS[r]} moves in steps of {step[r]:g} {unit} and its noise before rounding "
            f"({noise[r]:.2g} {unit}) is below half a step, so its rounding error follows the signal and would be read as "
            "effects")


def rounding_repeats(fit, theta_deg: np.ndarray, channels: tuple[np.ndarray, ...]):
    """``fit`` (a ``SegmentFit``) with each channel's covariance widened
    where its rounding error repeats: below the output step, a sample's
    rounding error is a function of the signal, so samples at the same
    angle (a step's, a rotation's phases recurring each few turns) share
    it. The fit took n independent errors; there are as many as distinct
    angles, n_eff: the rounding's share of the variance, Delta^2 / 12 of
    the residual variance sigma^2, grows by n / n_eff, weighted by how far
    the noise is below the step (``mean_rounding_variance``'s decay)."""
    if fit.status != "ok" or not np.isfinite(theta_deg).all():
        return fit
    step = output_step(np.column_stack(channels))
    distinct = np.unique(np.round(np.mod(theta_deg, 360.0), 6)).size
    share = np.divide(mean_rounding_variance(step, np.asarray(fit.sigma, float) ** 2), np.asarray(fit.sigma, float) ** 2,
                      out=np.zeros(3), where=np.asarray(fit.sigma) > 0)
    factor = 1.0 + np.minimum(share, 1.0) * (fit.n_samples / max(distinct, 1) - 1.0)
    # residuals that scatter less than the rounding alone would (few distinct angles, whose errors happen
    # to be small) do not measure it: the rounding's own variance, Delta^2 / 12 of a uniform error
    # (GUM 4.3.7), is taken instead
    factor = factor * np.maximum(share, 1.0)
    scale = np.repeat(np.sqrt(np.maximum(factor, 1.0)), 3)  # the covariance's order: channel, then (C, A, B)
    cov = fit.cov * np.outer(scale, scale)
    # below the step the rounding error is a function of the signal: a sine within a few steps (a channel
    # across the rotation axis), or angles that recur (their errors alias onto the sine), share it
    floor = rounding_covariance(step, fit.coef, theta_deg, np.asarray(fit.sigma, float) ** 2 - step**2 / 12.0)
    diagonal = np.diag(cov)
    widen = np.maximum(np.sqrt(np.divide(floor, diagonal, out=np.ones(9), where=diagonal > 0)), 1.0)
    cov = cov * np.outer(widen, widen) + np.diag(np.where(diagonal > 0, 0.0, floor))
    if np.array_equal(cov, fit.cov):
        return fit
    return replace(fit, cov=cov)


# a fitted sine of amplitude below this many steps: its rounded samples do not tell its amplitude and phase
SMALL_SINE_STEPS = 2.0
# sub-step places of the signal tried (a regular grid over one step: deterministic)
ROUNDING_TRIALS = 64


def rounding_covariance(step: np.ndarray, coef: np.ndarray, theta_deg: np.ndarray, noise_var: np.ndarray) -> np.ndarray:
    """(9,) per channel the mean square error that rounding to ``step``
    lends the fitted (C, A, B) of y = C + A sin(theta) + B cos(theta), by
    propagating the distribution (GUM Supplement 1): the fitted sine at the
    segment's own angles, moved by each of ``ROUNDING_TRIALS`` places
    within a step (where the true signal lies within its step is unknown,
    uniform), with Gaussian noise of ``noise_var`` (a fixed seed) added,
    rounded and fitted again. It holds what no closed form for independent
    errors does: a near-constant channel's one shared error (Delta^2 / 12
    in C), and the errors of angles that recur, aliased onto the sine.
    Only channels whose noise before rounding is below half a step (where
    the rounding is not dithered away: Widrow and Kollar 2008, ch. 5); 0
    elsewhere."""
    floor = np.zeros((3, 3))
    coarse = np.flatnonzero((step > 0) & (np.maximum(noise_var, 0.0) < (step / 2.0) ** 2))
    if coarse.size == 0 or theta_deg.size < 3:
        return floor.ravel()
    rad = np.radians(theta_deg)
    design = np.column_stack([np.ones(theta_deg.size), np.sin(rad), np.cos(rad)])
    solve = np.linalg.pinv(design)  # (3, n): the least-squares (minimum-norm) coefficients of any samples
    rng = np.random.default_rng(0)
    for r in coarse:
        delta, sigma = float(step[r]), float(np.sqrt(max(noise_var[r], 0.0)))
        signal = design @ coef[r]
        errors = np.empty((ROUNDING_TRIALS, 3))
        for j, place in enumerate((np.arange(ROUNDING_TRIALS) + 0.5) / ROUNDING_TRIALS - 0.5):
            true = signal + place * delta
            rounded = np.round((true + sigma * rng.standard_normal(true.size)) / delta) * delta
            error = rounded - true
            errors[j] = solve @ error
        floor[r] = np.mean(errors**2, axis=0)
        if np.hypot(coef[r, 1], coef[r, 2]) < SMALL_SINE_STEPS * delta:
            # a sine within a few steps is not known from its rounded samples (a few counts' sine at a step's
            # edge rounds to a square wave of amplitude 2 Delta / pi): the bounds of any rounding error's share,
            # Delta / 2 in C and 2 Delta / pi (a square wave's fundamental) in A and B, as rectangular
            # distributions (GUM 4.3.7)
            floor[r] = np.maximum(floor[r], np.array([delta**2 / 12.0, *((2.0 * delta / np.pi) ** 2 / 3.0,) * 2]))
    return floor.ravel()
