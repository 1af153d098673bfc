"""Whether a table recording's refined model predicts held-out segments
better than the baseline model.

The diagnosis selects effects by how much chi-square they remove from the
samples they were fitted to; a recommendation needs more: the model with
them must predict data it did not see. Each held-out unit is one segment
(or, where the segments are fewer than ``MIN_UNITS`` or leaving one out
leaves a parameter undetermined, one of ``BLOCKS`` consecutive blocks of
its samples). For a least-squares fit linearised at its optimum, the fit
without unit k moves the parameters by

    delta_k = (G - G_k)^-1 (b - b_k),

with G = J' W J and b = J' W r the weighted normal equations of every
sample and G_k, b_k those of unit k alone (the case-deletion update of
Cook and Weisberg 1982, Residuals and Influence in Regression), and unit
k's squared prediction error is
|r_k - J_k delta_k|^2_W = chi2_k - 2 delta_k' b_k + delta_k' G_k delta_k.
Both models are weighed alike (the refined model's noise per channel,
whitened as the diagnosis fits) and each unit's error is divided by its
number of residuals, so 1 is a unit predicted to its noise.

"Better by more than chance" is Wilcoxon's one-sided signed-rank test of
the per-unit log ratios of the two errors (``combine.heldout.signed_rank``;
exact up to 50 units without ties, normal beyond): a table's segments run at rates a decade
apart, so an effect's gain differs by orders of magnitude between them and
the paired t test of the static poses would take that spread for chance.
The test draws its chance from the units themselves, so segments that
scatter beyond their within-segment noise (a mounting that moves between
segments, an offset wandering from one to the next) count against an
effect that fits such scatter: it predicts some held-out segments better
and others worse.
"""

from __future__ import annotations

import copy

import numpy as np

from rotcal.combine.heldout import HeldOut, signed_rank
from rotcal.diagnose.fitting import ModelFit, fit_model
from rotcal.diagnose.model import Linearisation, Structure, weighted

MIN_UNITS = 12  # fewer segments than this: each is cut into blocks, so that the test has degrees of freedom
BLOCKS = 4     # blocks of a segment held out one at a time where the segment itself cannot be
CONDITION = 1e-10  # smallest eigenvalue (unit-diagonal scale) of the normal matrix without a unit that determines the rest


def held_out_units(fit: ModelFit) -> np.ndarray:
    """Each sample's held-out unit (-1: not used): its segment, or its
    block of the segment where the segments are too few."""
    segment = fit.obs.segment
    used = fit.use.any(axis=1)
    ids = np.unique(segment[used])
    blocks = BLOCKS if ids.size < MIN_UNITS else 1
    units = np.full(segment.size, -1)
    for k, s in enumerate(ids):
        at = np.flatnonzero(used & (segment == s))
        units[at] = k * blocks + (np.arange(at.size) * blocks) // max(at.size, 1)
    return units


def _unit_equations(lin: Linearisation, use: np.ndarray, idx: np.ndarray,
                    sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Unit ``use``'s weighted normal equations (G_k, b_k over ``idx``),
    its chi-square and its number of residuals, at the fit's parameters."""
    part = copy.copy(lin)  # the same parameters and cached columns; the unit's samples only
    part.use = use
    part.resid = np.where(use, lin.obs.whitened(lin.obs.y - lin.pred, use), 0.0)
    ev = part.evaluation(idx)
    G, b = weighted(ev, sigma)
    return G[np.ix_(idx, idx)], b[idx], float(np.sum(ev.rss / sigma**2)), int(use.sum())


def _split(units: np.ndarray, unit: int) -> np.ndarray:
    """``units`` with ``unit`` cut into ``BLOCKS`` consecutive blocks (numbered after the others)."""
    at = np.flatnonzero(units == unit)
    out = units.copy()
    out[at] = units.max() + 1 + (np.arange(at.size) * BLOCKS) // max(at.size, 1)
    return out


def _determined(rest: np.ndarray, every: np.ndarray) -> bool:
    """Whether the normal matrix without a unit (``rest``) still determines
    every parameter: its smallest eigenvalue on the scale of ``every``
    sample's (unit diagonal there) above ``CONDITION``; a parameter only the
    unit determines leaves a diagonal of rounding, of either sign."""
    scale = np.sqrt(np.diag(every))
    if np.any(scale == 0) or np.any(np.diag(rest) <= CONDITION * np.diag(every)):
        return False
    return bool(np.linalg.eigvalsh(rest / np.outer(scale, scale))[0] > CONDITION)


def _press(fit: ModelFit, units: np.ndarray, sigma: np.ndarray) -> tuple[np.ndarray, list[int]]:
    """Per unit, the mean squared weighted prediction error of ``fit``
    refitted without it, and the units left undetermined without them."""
    idx = fit.idx
    lin = Linearisation(fit.obs, fit.beta, fit.layout, fit.active, fit.clip, fit.structure, fit.use)
    ev = lin.evaluation(idx)
    G_all, b_all = (m[np.ix_(idx, idx)] if m.ndim == 2 else m[idx] for m in weighted(ev, sigma))
    errors, undetermined = [], []
    for k in range(int(units.max()) + 1):
        use = fit.use & (units == k)[:, None]
        if not use.any():
            errors.append(np.nan)
            continue
        G_k, b_k, chi2_k, n_k = _unit_equations(lin, use, idx, sigma)
        rest = G_all - G_k
        if not _determined(rest, G_all):
            undetermined.append(k)
            errors.append(np.nan)
            continue
        try:
            delta = np.linalg.solve(rest, b_all - b_k)
        except np.linalg.LinAlgError:  # singular to working precision after all: not predicted
            undetermined.append(k)
            errors.append(np.nan)
            continue
        errors.append(max(chi2_k - 2 * delta @ b_k + delta @ G_k @ delta, 0.0) / n_k)
    return np.array(errors), undetermined


def segments_held_out(final: ModelFit) -> tuple[HeldOut, str] | None:
    """The baseline (the diagnosis' null model on the same samples) and the
    model with the diagnosis' effects ``final`` compared on units held out
    one at a time, with what a unit is (segment, or segment block); None
    where the model has no effect or fewer than three units can be held out."""
    if not final.active:
        return None
    baseline = fit_model(final.obs, final.layout, final.beta, (), final.clip, Structure(), final.use)
    units = held_out_units(final)
    blocks = units.max() + 1 > np.unique(final.obs.segment[final.use.any(axis=1)]).size
    simple, gaps = _press(baseline, units, final.sigma)
    rich, more = _press(final, units, final.sigma)
    undetermined = sorted(set(gaps) | set(more))
    if undetermined:  # a segment that alone determines a parameter is held out by blocks
        for unit in undetermined:
            units = _split(units, unit)
        simple, _ = _press(baseline, units, final.sigma)
        rich, _ = _press(final, units, final.sigma)
        blocks = True
    ok = np.isfinite(simple) & np.isfinite(rich)
    if ok.sum() < 3:
        return None
    return signed_rank(simple[ok], rich[ok]), "segment block" if blocks else "segment"
