"""Fitting nested models of the diagnosis and scoring extensions.

A ``ModelFit`` is the Gauss-Newton optimum of one model (the null model plus
some extensions); the per-channel noise is re-estimated from its residuals,
so the weighted chi-square has one per degree of freedom. An extension's
score is the chi-square it would remove (one Gauss-Newton step from the
optimum: the likelihood-ratio statistic to first order), compared with
chi-square(k) for its false-alarm probability, and its BIC change uses the
per-channel residual sums of squares.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, field

import numpy as np
from scipy.special import chdtrc

from rotcal.diagnose.candidates import Candidate
from rotcal.diagnose.model import Evaluation, Layout, Linearisation, Observations, Structure, rss_after, solve, weighted

TOLERANCE = 1e-8  # Gauss-Newton stops when a step's chi-square reduction is below this per parameter
# A step whose chi-square reduction is below this many times the tolerance is
# followed by the optimum in every fit of the bench's default-plan datasets
# (Gauss-Newton converges quadratically: after steps of 7 to 4e5 times the
# tolerance the next reduction was below 1e-4 of it). A guess for speed
# only: where it is wrong, that iteration's step comes from the active
# columns alone, as in every iteration, and the results are the same.
LIKELY_LAST = 1e7


@dataclass(frozen=True, eq=False)
class ModelFit:
    obs: Observations
    layout: Layout
    beta: np.ndarray
    active: tuple[Candidate, ...]
    clip: tuple[float | None, float | None]
    structure: Structure
    use: np.ndarray
    ev: Evaluation
    sigma: np.ndarray
    G: np.ndarray
    b: np.ndarray
    idx: np.ndarray
    converged: bool  # Gauss-Newton stopped at its tolerance: ``ev`` is the evaluation at ``beta``
    # the offsets' wander between segments, which the whitened samples leave out (``offset_wander``; order ``idx``)
    wander_cov: np.ndarray | None = None
    # the scores of extensions already asked for (``score``), and the fit's own decrement
    memo: dict = field(default_factory=dict, init=False, repr=False)

    @property
    def n_total(self) -> int:
        return int(self.ev.n_used.sum())

    @property
    def n_params(self) -> int:
        extra = int(self.structure.step_t_s is not None and any(c.key == "unexplained@step" for c in self.active))
        return int(self.idx.size) + extra + sum(v is not None for v in self.clip)

    @property
    def bic(self) -> float:
        return bic(self.ev.rss, self.ev.n_used, self.n_params, self.n_total, self.obs.noise_floor)

    @property
    def residuals(self) -> np.ndarray:
        """The used samples' residuals (n, 3) in the output unit, not whitened."""
        return self.ev.resid if self.obs.whitening is None else np.where(self.use, self.obs.y - self.ev.pred, 0.0)

    @property
    def rms(self) -> float:
        return float(np.sqrt(self.ev.rss.sum() / self.n_total))

    def covariance(self) -> np.ndarray:
        """Covariance of the active parameters (order ``idx``): the
        pseudo-inverse of the normal matrix scaled to unit diagonal (as
        ``solve``). Unscaled, the parameters' scales span 1e15 where a rate
        error is fitted, and the pseudo-inverse's cut-off lost three digits:
        the last bits of G moved refined uncertainties by 3e-3. With the
        offsets' wander between segments where it was measured."""
        G = self.G[np.ix_(self.idx, self.idx)]
        scale = np.sqrt(np.diag(G))
        scale[scale == 0] = 1.0
        outer = np.outer(scale, scale)
        cov = np.linalg.pinv(G / outer) / outer
        return cov if self.wander_cov is None else cov + self.wander_cov

    def param_block(self, cand: Candidate) -> tuple[np.ndarray, np.ndarray]:
        """(values, covariance) of an active extension's parameters."""
        pos = np.searchsorted(self.idx, self.layout.params(cand))
        return self.beta[self.layout.params(cand)], self.covariance()[np.ix_(pos, pos)]


def chi2_sf(x: float, dof: float) -> float:
    """The chi-square survival function, as ``scipy.stats.chi2.sf`` (1 below
    the support) without its per-call argument handling: the selection
    evaluates it hundreds of times per dataset (0.1 ms each through ``chi2.sf``)."""
    return float(chdtrc(dof, max(x, 0.0)))


def bic(rss: np.ndarray, n_used: np.ndarray, k: int, n_total: int, floor: np.ndarray) -> float:
    """Bayesian information criterion with each channel's noise profiled
    (never below its numerical ``floor``)."""
    return float(np.sum(n_used * np.log(np.maximum(rss / n_used, floor**2))) + k * np.log(n_total))


def active_indices(layout: Layout, active: tuple[Candidate, ...]) -> np.ndarray:
    idx = [np.arange(layout.n_base)] + [layout.params(c) for c in active]
    return np.sort(np.concatenate(idx))


def _sigma(ev: Evaluation, layout: Layout, idx: np.ndarray, obs: Observations) -> np.ndarray:
    """Each channel's noise from its residuals, never below the numerical floor."""
    active = layout.mask(idx)
    k = np.array([active[channel].sum() for channel in layout.per_channel])
    return np.maximum(np.sqrt(ev.rss / np.maximum(ev.n_used - k, 1)), obs.noise_floor)


def fit_model(obs: Observations, layout: Layout, beta: np.ndarray, active: tuple[Candidate, ...],
              clip: tuple[float | None, float | None], structure: Structure, use: np.ndarray,
              max_iter: int = 40) -> ModelFit:
    """Gauss-Newton to the optimum of the null model plus ``active``.

    Parameters of extensions not in ``active`` are held at zero. The null
    model alone (no extension, no step) is linear in its parameters, so its
    optimum does not depend on the start: it is fitted once for each clip
    and mask, and asking again (the findings' models without a detected
    effect, an elimination back to it) returns that fit while it is held
    (a weak reference kept with the observations: a strong one would make
    a cycle through ``ModelFit.obs`` that pins the observations' design
    buffers until the garbage collector runs).
    """
    null = ("null fit", layout, clip, use.tobytes()) if not active and structure == Structure() else None
    held = obs.reuse[null]() if null in obs.reuse else None
    if held is not None:
        return held
    # Hand-written rather than scipy's least_squares, which needs the dense
    # Jacobian: on the default plan's demo (54,000 samples, 90 parameters)
    # that is 3 x 54,000 x 90 doubles = 117 MB per evaluation (216 MB at
    # [diagnosis] max_samples), where the per-channel normal equations that
    # the compact design accumulates are 3 x 90 x 90 doubles = 194 kB.
    beta = beta.copy()
    idx = active_indices(layout, active)
    inactive = np.setdiff1d(np.arange(beta.size), idx)
    beta[inactive] = 0.0
    lin: Linearisation | None = None
    full: Evaluation | None = None   # the evaluation with every column, once built
    converged = likely = False
    for _ in range(max_iter):
        # the last iteration's columns and designs go before the next ones are built: its design
        # buffers, still in the cache, serve the next evaluation (``geometry.design_buffer``)
        lin = ev = full = None
        lin = Linearisation(obs, beta, layout, active, clip, structure, use)
        # the step needs only the active parameters' columns; the optimum needs every column,
        # built at once where the last step makes this iteration likely to be the optimum
        full = lin.evaluation() if likely else None
        ev = full if full is not None else lin.evaluation(idx)
        sigma = _sigma(ev, layout, idx, obs)
        G, b = weighted(ev, sigma)
        step, decrement = solve(G, b, idx)
        converged = decrement < TOLERANCE * max(idx.size, 1)
        if converged:
            break
        if full is not None:   # not the optimum: the step from the active columns alone, as in every iteration
            ev = full = None
            ev = lin.evaluation(idx)
            G, b = weighted(ev, sigma)
            step, decrement = solve(G, b, idx)
        beta[idx] += step
        likely = decrement < LIKELY_LAST * TOLERANCE * max(idx.size, 1)
    if lin is None:
        raise ValueError("fit_model needs max_iter >= 1")
    if full is None:   # at the optimum every column: the scores of the extensions not in the model
        ev = None
        ev = full = lin.evaluation()
        G, b = weighted(ev, sigma)
    fit = ModelFit(obs, layout, beta, active, clip, structure, use, full, sigma, G, b, idx, converged)
    if null is not None:
        obs.reuse[null] = weakref.ref(fit)
    return fit


@dataclass(frozen=True)
class Score:
    """What adding ``candidate`` to a fit would do (linearised)."""

    candidate: Candidate
    chi2: float
    p_value: float
    delta_bic: float
    rss: np.ndarray


def score(fit: ModelFit, cands: tuple[Candidate, ...], p_value: float | None = None,
          ev: Evaluation | None = None, extra_params: int = 0) -> Score:
    """Score of adding ``cands`` jointly to ``fit``; ``ev`` supplies the
    Jacobian when the extension changes the structure (a step time). The
    selection, the exchange and the findings ask for the same scores of one
    fit again: they are kept with it."""
    if ev is None and p_value is None and not extra_params:
        key = tuple(c.key for c in cands)
        if key not in fit.memo:
            fit.memo[key] = _score(fit, cands, None, fit.ev, 0)
        return fit.memo[key]
    return _score(fit, cands, p_value, ev or fit.ev, extra_params)


def _score(fit: ModelFit, cands: tuple[Candidate, ...], p_value: float | None, ev: Evaluation,
           extra_params: int) -> Score:
    G, b = weighted(ev, fit.sigma) if ev is not fit.ev else (fit.G, fit.b)
    extra = np.concatenate([fit.layout.params(c) for c in cands])
    idx = np.union1d(fit.idx, extra)
    step, _ = solve(G, b, idx)
    # the optimum's own gradient is ~0: the decrease is the extension's share
    if ev is not fit.ev:
        _, base_dec = solve(G, b, fit.idx)
    else:
        if "decrement" not in fit.memo:
            fit.memo["decrement"] = solve(G, b, fit.idx)[1]
        base_dec = fit.memo["decrement"]
    dchi = max(float(b[idx] @ step) - base_dec, 0.0)
    rss = np.maximum(rss_after(ev, step, idx), 1e-300)
    k = extra.size + extra_params
    dbic = bic(rss, ev.n_used, fit.n_params + k, fit.n_total, fit.obs.noise_floor) - fit.bic
    p = chi2_sf(dchi, extra.size) if p_value is None else p_value
    return Score(cands[0], dchi, p, dbic, rss)


def swap_bic(fit: ModelFit, drop: Candidate, add: Candidate) -> float:
    """Linearised BIC of the model with ``drop`` replaced by ``add``: from
    the optimum, set ``drop``'s parameters to zero and refit the rest with
    ``add`` (one Gauss-Newton step on the same Jacobian)."""
    layout = fit.layout
    out = layout.params(drop)
    keep = np.setdiff1d(fit.idx, out)
    idx = np.union1d(keep, layout.params(add))
    beta_out = fit.beta[out]
    grad = fit.b.copy()
    grad[idx] += fit.G[np.ix_(idx, out)] @ beta_out  # the gradient once drop's parameters are zero
    step, _ = solve(fit.G, grad, idx)
    full = np.concatenate([step, -beta_out])
    order = np.concatenate([idx, out])
    rss = np.maximum(rss_after(fit.ev, full, order), 1e-300)
    return bic(rss, fit.ev.n_used, fit.n_params - out.size + layout.params(add).size, fit.n_total, fit.obs.noise_floor)


def without(fit: ModelFit, drop: tuple[Candidate, ...]) -> ModelFit:
    """The same model refitted without the extensions ``drop``."""
    keys = {c.key for c in drop}
    active = tuple(c for c in fit.active if c.key not in keys)
    structure = fit.structure if any(c.key == "unexplained@step" for c in active) else Structure()
    return fit_model(fit.obs, fit.layout, fit.beta, active, fit.clip, structure, fit.use)

