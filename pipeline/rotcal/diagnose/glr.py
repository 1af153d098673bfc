"""The generalized likelihood-ratio (GLR) test of a known nested model: the
best test of one effect, the yardstick of the diagnosis's power curves
(docs/power.md, scripts/power_curves.py).

The null model is the diagnosis's baseline with every parameter fitted
(``fitting.fit_model`` with no extension); the alternative adds the true
effect's own extensions (its ``Candidate``s, the effect's exact shape) with
their parameters free. Each channel's noise is profiled, so twice the
log-likelihood ratio is the chi-square drop

    Lambda = sum_r n_r ln(RSS_0,r / RSS_1,r),

chi-square(k) under the null for k free parameters (Wilks 1938), and the
asymptotically most powerful test of that one alternative. Knowing which
effect, on which axis or channel, it tests once where the diagnosis
searches the whole catalogue, but it faces the same absorption of the
effect by the fitted baseline.

Clipping is not a smooth extension: its GLR is that of quantized samples
with an output limit c at the largest output (its maximum-likelihood value),
each sample at c censored (probability P(x >= c - q/2)) rather than in its
quantum bin (P(c - q/2 <= x < c + q/2)), x ~ N(mu, sigma^2) the null model's
prediction and noise (``clipping.censoring_gain``). Its null distribution
is not chi-square; it is drawn by Monte Carlo (``clipping_threshold``).
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.clipping import censoring_gain
from rotcal.diagnose.fitting import ModelFit, fit_model
from rotcal.diagnose.model import Layout, Observations, Structure
from rotcal.model.effects.base import Candidate


def null_fit(obs: Observations, layout: Layout, start: np.ndarray) -> ModelFit:
    """The baseline model with every parameter fitted, as the diagnosis starts."""
    return fit_model(obs, layout, start, (), (None, None), Structure(), np.ones_like(obs.y, bool))


def glr(null: ModelFit, true: tuple[Candidate, ...]) -> tuple[float, int]:
    """(Lambda, k): twice the log-likelihood ratio of ``null`` plus the
    extensions ``true`` (refitted from the null's optimum) against ``null``,
    each channel's noise profiled, and the number of added parameters."""
    alt = fit_model(null.obs, null.layout, null.beta, true, null.clip, null.structure, null.use)
    stat = float(np.sum(null.ev.n_used * np.log(null.ev.rss / alt.ev.rss)))
    return max(stat, 0.0), sum(len(c.names) for c in true)


def clipping_glr(null: ModelFit, q: float) -> float:
    """Lambda of an upper output limit at the largest output value (common to
    every channel, as the converter's limit is), given the null model's
    predictions and per-channel noise; ``q`` the output quantum."""
    y = null.obs.y
    limit = float(y.max())
    at = y == limit
    sigma = np.broadcast_to(null.sigma[None, :], y.shape)
    return float(2 * censoring_gain(null.ev.pred[at], sigma[at], limit, q).sum())


def clipping_threshold(null: ModelFit, q: float, alpha: float, draws: int, rng: np.random.Generator,
                       span_sigma: float = 7.0, chunk: int = 2000) -> float:
    """The (1 - ``alpha``) quantile of ``clipping_glr`` under the null model
    by Monte Carlo: ``draws`` quantized noise realisations of the samples
    whose prediction lies within ``span_sigma`` of the largest (the others
    reach the top value with negligible probability)."""
    mu, sigma = null.ev.pred, np.broadcast_to(null.sigma[None, :], null.obs.y.shape)
    near = mu >= mu.max() - span_sigma * sigma.max()
    mu, sigma = mu[near], sigma[near]
    stats = []
    for start in range(0, draws, chunk):
        x = q * np.round((mu[None, :] + sigma[None, :] * rng.standard_normal((min(chunk, draws - start), mu.size))) / q)
        top = x.max(axis=1, keepdims=True)
        gain = np.where(x == top, censoring_gain(mu[None, :], sigma[None, :], top, q), 0.0)
        stats.append(2 * gain.sum(axis=1))
    return float(np.quantile(np.concatenate(stats), 1 - alpha))
