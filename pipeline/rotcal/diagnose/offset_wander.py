"""The offsets' wander between segments in the final model's covariance.

The model is fitted to the samples whitened within segments (``noise``: a
first-order filter white at zero frequency, a level per rate and axis), so
its covariance holds the noise a segment's own samples show and not a
wander of the sensor's bias slower than a segment, which moves every
sample of a segment alike and neighbouring segments alike. Whatever the
model reads from segments' offsets (the offsets themselves, an axis tilt's
shift of its axis's segments, a centripetal offset, a drift) is then
stated several times too precisely: under the mixed noise of
``scripts/noise_coverage.py`` tilts 0.005 to 0.01 degree off at 0.00035
uncertainty.

So, where the fits measured a wander (``wander.OffsetNoise.wanders``), the
wander is measured on the final model's residuals: per channel, the
whitened residuals summed over each segment's whitened indicator, whose
covariance under a wander of covariance q^2 rho between segments (rho
independent, Gauss-Markov or a random walk: ``wander.wander_shapes``) is
known once the fitted parameters' share is taken off (``fitted_wander``); q and rho by maximum likelihood on
what the parameters leave free (restricted maximum likelihood, Patterson
& Thompson 1971). A wander w moves the estimates by G^-1 J' W E w (E the
segments' indicators, whitened as the samples), so the covariance gains

    G^-1 (sum_r J_r' W_r E_r (q_r^2 rho_r) E_r' W_r J_r) G^-1,

the sandwich of the wander's segment-level covariance. Each extension is
then tested again by its parameters' Wald statistic under that covariance
(``wander_tested``), as the selection's backward elimination does under
the whitened one: one the wander explains is dropped, the model refitted
and the wander measured again. White noise (no wander measured) leaves
the model and its covariance as they were.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from rotcal.diagnose.candidates import STEP, Candidate
from rotcal.diagnose.fitting import ModelFit, chi2_sf, without
from rotcal.diagnose.scans import p_is
from rotcal.diagnose.wander import OffsetNoise, wander_shapes
from rotcal.model.effects import catalogue

Q_GRID = np.r_[0.0, np.geomspace(0.03, 3.0, 24)]   # the wander's sd as shares of the means' spread
# directions of the segments' sums the parameters all but absorb (below this share of the largest freedom):
# what is left there is the parameters' compromise between segments' means and their samples' shapes, not a
# measure of the wander (one tilt direction at 1e-3 held 27 sigma and asked for a wander of 85 counts)
ABSORBED = 0.05


def _log_likelihood(m: np.ndarray, v: np.ndarray) -> float:
    """Gaussian log-likelihood (without constants) of ``m`` ~ N(0, ``v``)."""
    chol = np.linalg.cholesky(v)
    white = np.linalg.solve(chol, m)
    return -float(np.sum(np.log(np.diag(chol)))) - 0.5 * float(white @ white)


def fitted_wander(sums: np.ndarray, free: np.ndarray, noise_var: float, shapes: list[np.ndarray]) -> np.ndarray:
    """The wander's covariance between segments (maximum likelihood over
    q and the shapes) from one channel's whitened residuals summed over
    each segment's whitened indicator, ``sums`` = E' r. Under a wander w
    of covariance q^2 rho, E' r = N w + E' (I - P) e with ``free`` N =
    E' (I - P) E, P the model's projection: the fitted parameters took
    their share, so cov(E' r) = N q^2 rho N + sigma^2 N (``noise_var``
    sigma^2), taken on N's range (restricted maximum likelihood). Zeros
    where no wander fits better than none."""
    out = np.zeros((sums.size, sums.size))
    lam, vec = np.linalg.eigh(free)
    keep = lam > lam.max() * ABSORBED
    if keep.sum() < 2:
        return out
    lam, vec = lam[keep], vec[:, keep]
    z = vec.T @ sums
    white = np.diag(noise_var * lam)
    spread = float(np.sqrt(np.mean((z / lam) ** 2)))   # of the segments' mean residuals
    best = (_log_likelihood(z, white), 0.0, shapes[0])
    for q in spread * Q_GRID[1:]:
        for rho in shapes:
            moved = lam[:, None] * (vec.T @ rho @ vec) * lam[None, :]
            ll = _log_likelihood(z, white + q**2 * moved)
            if ll > best[0]:
                best = (ll, q, rho)
    return best[1] ** 2 * best[2]


def with_offset_wander(final: ModelFit, noise: OffsetNoise) -> ModelFit:
    """``final`` whose covariance holds the offsets' wander between segments
    (module docstring); unchanged without a measured wander."""
    if not noise.wanders:
        return final
    seg = final.obs.segment
    ids, idx = np.unique(seg, return_inverse=True)
    t = final.obs.motion.t_s
    start, stop = np.full(ids.size, np.inf), np.full(ids.size, -np.inf)
    np.minimum.at(start, idx, t)
    np.maximum.at(stop, idx, t)
    shapes, _, walk = wander_shapes(start, stop)
    duration = float(stop.max() - start.min())
    if duration > 0:   # the walk per unit variance at the record's end
        shapes = [*shapes, walk / duration]
    indicator = (idx[:, None] == np.arange(ids.size)[None, :]).astype(float)
    p = final.beta.size
    base = final.covariance()
    spread = np.zeros_like(base)
    for r, design in enumerate(final.ev.designs):
        ew = design.rows_of(indicator)   # the segments' indicators as the model's whitened rows
        counts = np.sum(ew**2, axis=0)
        on = counts > 0
        if on.sum() < 3:
            continue
        ew = ew[:, on]
        jte = np.zeros((p, ew.shape[1]))
        jte[np.concatenate([design.base.ravel(), design.ext])] = design.transposed_times(ew)
        b = jte[final.idx] / final.sigma[r] ** 2   # J' W E
        free = np.diag(counts[on]) - final.sigma[r] ** 2 * b.T @ base @ b
        cov = fitted_wander(ew.T @ design.resid, free, float(final.sigma[r] ** 2), [s[np.ix_(on, on)] for s in shapes])
        if np.any(cov):
            spread += b @ cov @ b.T
    if not np.any(spread):
        return final
    return replace(final, wander_cov=base @ spread @ base)


def wald_test(final: ModelFit, cand: Candidate) -> tuple[float, float]:
    """(chi-square, p) of the extension's parameters against zero under
    ``final``'s covariance (Wald)."""
    value, block = final.param_block(cand)
    stat = float(value @ np.linalg.pinv(block) @ value)
    return stat, chi2_sf(stat, value.size)


def wander_tested(final: ModelFit, noise: OffsetNoise, alpha: float) -> tuple[ModelFit, dict[str, str]]:
    """``final`` with the wander between segments in its covariance
    (``with_offset_wander``) and without the slow effects (those that move
    segments' offsets or vary in time or temperature, and the step) whose
    parameters that covariance leaves within their uncertainty (Wald
    at ``alpha``), one at a time, the least significant first; per effect
    the sentence its row adds."""
    texts: dict[str, str] = {}
    # the wander moves whole segments slowly: it can explain what moves segments' offsets or varies slowly in
    # time or temperature (a warm-up), not a harmonic within segments (a quadratic nonlinearity's second
    # harmonic was set aside at Wald 4.3 beside chi-square 116 on the noise's spectrum, its constant part's
    # share of the wander widening it), whose uncertainty it still widens
    movers = {e.name for e in catalogue() if e.moves_segment_offsets or e.at_rest in ("time", "temperature")}
    final = with_offset_wander(final, noise)
    while final.wander_cov is not None and any(c == STEP or c.effect in movers for c in final.active):
        wald = []
        for cand in [c for c in final.active if c == STEP or c.effect in movers]:
            stat, p = wald_test(final, cand)
            wald.append((p, cand.key, cand, stat))
        p, _, worst, stat = max(wald)
        if p < alpha:
            break
        text = (f"{worst.key} set aside: with the offsets' wander between segments in its uncertainty its "
                f"parameters are within noise (Wald chi-square {stat:.1f} on {len(worst.names)}, {p_is(p)})")
        texts[worst.effect] = f"{texts[worst.effect]}; {text}" if worst.effect in texts else text
        final = with_offset_wander(without(final, (worst,)), noise)
    return final, texts
