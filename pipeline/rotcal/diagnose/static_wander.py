"""The slow effects of a static diagnosis tested against a wander of the
offsets (``rotcal.diagnose.static``).

An offset that wanders slower than a pose (Gauss-Markov, flicker, random
walk) shifts the poses' means together over time, and within a session of
minutes its path resembles a drift or a warm-up. The diagnosis's F test
takes the scatter beyond the poses' noise as independent between poses, so
such a wander reads as ``offset_drift`` (3 of 50 clean hand sessions under
a Gauss-Markov wander of 470 to 730 s, p 6e-5 to 1e-4). An effect whose
parameters act through time or temperature is therefore kept only where it
explains the poses better than a wander does: the likelihood ratio of the
effect with the wander's size and shape fitted under both hypotheses, as
the table diagnosis tests its offset effects (``diagnose.wander``), at
``WANDER_LEVEL``. Where the model with the effect leaves no scatter beyond
the poses' own noise, no wander competes and the test is not made.

The poses' residuals are those of the linearised static model (whitened by
the poses' weights), so every channel's wander reaches them through the
offsets' columns J_O of its Jacobian: the wander's covariance is
q^2 (J_O J_O') o S, S one of ``wander_shapes`` between the poses (the
poses' independent scatter among them), q common to the channels. The
likelihoods are those of the contrasts free of the other parameters
(restricted maximum likelihood, Patterson & Thompson 1971).
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.wander import wander_shapes
from rotcal.model.effects import effect_named
from rotcal.model.effects.base import Candidate

SLOW = frozenset({"time", "temperature"})  # the effects whose parameters act through them (``Effect.at_rest``)
Q_GRID = np.geomspace(0.03, 10.0, 16)      # the wander's size, relative to the contrasts' spread
# The effect was found at the false-alarm rate against independent scatter; this level asks which of two
# explanations the evidence favours. Clean hand sessions under a Gauss-Markov wander: the drifts the F test
# named had p 0.017 to 0.12 here; drifts of 0.025 count/s under white noise 6e-5 to 8e-4.
WANDER_LEVEL = 0.01


def is_slow(cand: Candidate) -> bool:
    return effect_named(cand.effect).at_rest in SLOW


def wander_p_value(residuals: np.ndarray, jacobian: np.ndarray, fixed: np.ndarray, tested: np.ndarray,
                   offsets: np.ndarray, noise: np.ndarray, pose_of_row: np.ndarray, bounds_s: np.ndarray) -> float:
    """The p-value of the columns ``tested`` of ``jacobian`` against a
    wander, the columns ``fixed`` fitted beside them: 2 ln LR on
    len(tested) degrees of freedom. ``residuals`` at the linearisation
    point, ``offsets`` the offsets' columns, ``noise`` the whitened
    residuals' covariance of the poses' own noise, ``pose_of_row`` each
    residual's pose and ``bounds_s`` each pose's first and last time (s)."""
    u, sv, _ = np.linalg.svd(jacobian[:, fixed], full_matrices=True)
    rank = int(np.sum(sv > sv[0] * 1e-9)) if sv.size and sv[0] > 0 else 0
    basis = u[:, rank:]   # the contrasts free of the fixed parameters
    k = tested.size
    if basis.shape[1] <= k + 1:
        return 1.0
    m, x = basis.T @ residuals, basis.T @ jacobian[:, tested]
    shapes, _, walk = wander_shapes(bounds_s[:, 0], bounds_s[:, 1])
    duration = float(np.ptp(bounds_s))
    if duration > 0:
        shapes = [*shapes, walk / duration]
    reach = jacobian[:, offsets] @ jacobian[:, offsets].T
    local = np.stack([basis.T @ (reach * s[np.ix_(pose_of_row, pose_of_row)]) @ basis for s in shapes])
    q = np.r_[0.0, float(np.sqrt(np.mean(m**2))) * Q_GRID]
    v = basis.T @ noise @ basis + q[:, None, None, None] ** 2 * local[None]
    chol = np.linalg.cholesky(v)
    wm = np.linalg.solve(chol, np.broadcast_to(m[:, None], v.shape[:-1] + (1,)))[..., 0]
    wx = np.linalg.solve(chol, np.broadcast_to(x, v.shape[:-1] + (k,)))
    logdet = 2 * np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    null = logdet + np.sum(wm**2, -1)
    # the alternative at each grid point's own best parameters (generalised least squares), then the best point
    gram = np.einsum("...ij,...ik->...jk", wx, wx)
    proj = np.einsum("...ij,...i->...j", wx, wm)
    explained = np.einsum("...j,...j->...", proj, np.linalg.solve(gram, proj[..., None])[..., 0])
    stat = max(0.0, float(null.min() - (null - explained).min()))
    return chi2_sf(stat, k)
