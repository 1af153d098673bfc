"""The static poses' model with catalogue effects: the residuals a static
diagnosis tests (``rotcal.diagnose.static``).

A static pose k has its mean output m_k (three channels), the covariance of
that mean, its mid-time t_k and, where logged, its mean temperature T_k. The
forward model of docs/effects.md, restricted to what a DUT at rest can show,
is per channel r

    m_kr = O_r + rho_r (t_k - t0) + tco_r (T_k - T_ref)
           + (1 + tcs_r (T_k - T_ref)) y_kr (1 + k2_r u_kr) (1 + k3_r u_kr^2),

y_kr = r_r . a_k the linear output and u_kr = y_kr / x1g_r (x1g_r = g |r_r|,
the channel's output at 1 g), t0 the recording's first sample and T_ref the
poses' mean temperature (sample-weighted: the mean of the samples the model
sees, as in the table diagnosis). The effects are ``offset_drift``,
``thermal``, ``quadratic_nonlinearity`` and ``cubic_nonlinearity`` of the
catalogue, with its parameter names.

Two residuals, after the two static fits (``combine.static``):

- orientation-free poses (``multiposition``): the model inverted per pose
  (offset and thermal terms removed, the gains divided out by fixed-point
  iteration), a_k = L^-1 y_k, and the residual |a_k| - g_local divided by the
  fit's standard deviation per pose (pose noise and excess scatter);
- poses of known reference (labels, jig; ``poses.reference_fit``): the
  vector residual m_k - model(ref_k), whitened by the pose's covariance plus
  the fit's excess covariance (Geist 2017 Eq. 19 with the effects added).

Parameters: the static fit's own (L's six elements and O, or C's nine and
O), then every effect parameter; the Jacobian is taken by central
differences over the parameters (a few dozen; every pose at once).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import block_diag

from rotcal.combine import StaticReduction
from rotcal.combine.multiposition import (
    FULL,
    ORTHOGONAL,
    TRIL,
    VARIANCE_FLOOR,
    OrientationFreeFit,
    excess_variance,
    magnitude_and_gradient,
    pose_arrays,
)
from rotcal.combine.poses import ReferenceFit, references
from rotcal.fit.lsq import ols
from rotcal.model.conventions import CHANNELS
from rotcal.model.effects import listed
from rotcal.model.effects.base import Candidate

# a parameter's typical size, for the central-difference step (internal names by prefix; ``Effect.at_rest_steps``)
_STEP = {prefix: step for e in listed() for prefix, step in e.at_rest_steps.items()}


@dataclass(frozen=True, eq=False)
class PoseModel:
    """The poses and the static fit a diagnosis extends: pose means (n, 3),
    their mid-times since the first sample (s; None without time stamps),
    temperature excursions T - T_ref (K; None unless logged and varying),
    the references (n, 3, g; None when orientation-free), the weights (the
    orientation-free residual's standard deviation per pose, (n,), or the
    lower Cholesky factors of the vector residual's covariance, (n, 3, 3)),
    the start parameters, which of them are free, the candidate extensions
    and g_local."""

    means: np.ndarray
    elapsed_s: np.ndarray | None
    excursion_k: np.ndarray | None
    reference: np.ndarray | None
    weights: np.ndarray
    start: np.ndarray
    free: np.ndarray
    candidates: tuple[Candidate, ...]
    g_local: float
    excess: bool           # the weights hold an estimated excess scatter (the tests then use F)
    noise: np.ndarray      # the weighted residuals' covariance of the poses' own noise (n_residuals, n_residuals)
    bounds_s: np.ndarray | None  # each pose's first and last sample time since the first sample (s)

    @property
    def offsets(self) -> np.ndarray:
        """The offsets' columns in the parameter vector."""
        return np.arange(6, 9) if self.reference is None else np.arange(9, 12)

    @property
    def pose_of_row(self) -> np.ndarray:
        return np.repeat(np.arange(len(self.means)), self.n_residuals // len(self.means))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for c in self.candidates for n in c.names)

    @property
    def n_base(self) -> int:
        return self.start.size

    @property
    def n_residuals(self) -> int:
        return self.means.size if self.reference is not None else len(self.means)

    def columns(self, cand: Candidate) -> list[int]:
        """The candidate's columns in the full parameter vector."""
        names = self.names
        return [self.n_base + names.index(n) for n in cand.names]

    def full(self, base: np.ndarray, effects: dict[str, float] | None = None) -> np.ndarray:
        values = effects or {}
        return np.concatenate([base, [values.get(n, 0.0) for n in self.names]])

    def residuals(self, theta: np.ndarray) -> np.ndarray:
        """The weighted residuals of every pose under the parameters ``theta``."""
        values = dict(zip(self.names, theta[self.n_base:]))
        n = len(self.means)
        coef = {p: np.array([values.get(f"{p}_{c}", 0.0) for c in CHANNELS]) for p in _STEP}
        offset = np.zeros((n, 3))
        scale = np.ones((n, 3))
        if self.elapsed_s is not None:
            offset += coef["drift"][None] * self.elapsed_s[:, None]
        if self.excursion_k is not None:
            offset += coef["tco"][None] * self.excursion_k[:, None]
            scale = scale + coef["tcs"][None] * self.excursion_k[:, None]

        def gain(u: np.ndarray) -> np.ndarray:
            return (1.0 + coef["k3"][None] * u**2) * (1.0 + coef["k2"][None] * u)

        if self.reference is None:
            L = np.zeros((3, 3))
            L[TRIL] = theta[:6]
            y = (self.means - theta[6:9] - offset) / scale
            x1g = np.linalg.norm(L, axis=1) * self.g_local
            linear = y
            for _ in range(4):   # y = y_lin f(y_lin / x1g): converges as (k u)^n
                linear = y / gain(linear / x1g)
            a = np.linalg.solve(L, linear.T).T
            return (np.linalg.norm(a, axis=1) - self.g_local) / self.weights
        C = theta[:9].reshape(3, 3)
        y = self.reference @ C.T
        predicted = theta[9:12] + offset + scale * y * gain(y / np.linalg.norm(C, axis=1))
        return np.linalg.solve(self.weights, (self.means - predicted)[:, :, None])[:, :, 0].ravel()

    def jacobian(self, theta: np.ndarray, columns: np.ndarray) -> np.ndarray:
        """d residuals / d theta[columns] by central differences."""
        out = np.empty((self.n_residuals, columns.size))
        base_scale = np.abs(theta[: self.n_base]).max()
        for j, col in enumerate(columns):
            if col < self.n_base:
                h = 1e-6 * max(abs(theta[col]), 1e-3 * base_scale)
            else:
                h = _STEP[self.names[col - self.n_base].split("_")[0]]
            up, down = theta.copy(), theta.copy()
            up[col] += h
            down[col] -= h
            out[:, j] = (self.residuals(up) - self.residuals(down)) / (2 * h)
        return out

    def state(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The intrinsic state (g r rows, O) of ``theta`` and d state / d theta[:n_base] (12, n_base)."""
        if self.reference is not None:
            return theta[:12].copy(), np.eye(12)
        L = np.zeros((3, 3))
        L[TRIL] = theta[:6]
        lift = np.zeros((12, 9))
        for j, (r, c) in enumerate(zip(*TRIL)):
            lift[3 * r + c, j] = self.g_local
        lift[9:, 6:] = np.eye(3)
        return np.concatenate([(self.g_local * L).ravel(), theta[6:9]]), lift


def pose_model(static: StaticReduction, t0_ns: int | None) -> PoseModel | None:
    """The ``PoseModel`` of a static reduction (None when it has no fit, no
    residual degree of freedom or poses without scatter): the effects testable on its poses (time stamps for ``offset_drift``, a
    varying temperature for ``thermal``)."""
    fit = static.fit
    if fit is None:
        return None
    poses = static.positions
    means, cov = pose_arrays(poses)
    times = poses.select("t_start_ns", "t_end_ns").to_numpy().astype(float)
    bounds = None if t0_ns is None or not np.isfinite(times).all() else (times - t0_ns) / 1e9
    elapsed = None if bounds is None else bounds.mean(axis=1)
    temperature = poses["temperature_c"].to_numpy().astype(float)
    excursion = None
    if np.isfinite(temperature).all() and np.ptp(temperature) > 0:
        counts = poses["n_samples"].to_numpy().astype(float)
        excursion = temperature - np.average(temperature, weights=counts)
    # the catalogue effects a DUT at rest can show (``Effect.at_rest``), those whose quantity the poses carry
    have = {"pose": True, "time": elapsed is not None, "temperature": excursion is not None}
    cands = tuple(c for e in listed() if e.at_rest is not None and have[e.at_rest]
                  for c in e.candidates((), (), False))
    # poses without scatter (noise-free, or identical samples with no output step known) or a fit with
    # no residual degree of freedom leave nothing to test an effect against
    if isinstance(fit, OrientationFreeFit):
        L = fit.result.state[:9].reshape(3, 3) / fit.result.g_local
        start = np.concatenate([L[TRIL], fit.result.state[9:]])
        free = ORTHOGONAL if static.model == "orthogonal" else FULL
        noise_var, tau2 = _scalar_scatter(fit, start, means, cov, free.size)
        variance = noise_var + tau2
        if not np.all(variance > 0):
            return None
        return PoseModel(means, elapsed, excursion, None, np.sqrt(variance), start, free, cands,
                         fit.result.g_local, tau2 > 0, np.diag(noise_var / variance), bounds)
    excess_cov = fit.excess_cov if not isinstance(fit, ReferenceFit) or fit.pose_cov is None else _vector_excess(means, cov, references(poses))
    weight = cov + excess_cov[None]
    if fit.dof == 0 or not np.all(np.linalg.eigvalsh(weight) > 0):
        return None
    chol = np.linalg.cholesky(weight)
    inner = np.linalg.solve(chol, cov)
    noise = np.linalg.solve(chol, np.swapaxes(inner, 1, 2))   # L^-1 cov L^-T, pose by pose
    return PoseModel(means, elapsed, excursion, references(poses), chol, fit.result.state.copy(), np.arange(12),
                     cands, fit.result.g_local, bool(np.any(excess_cov != 0)), block_diag(*noise), bounds)


# The tests weigh each pose by its own noise and an excess scatter common to the poses, estimated from the
# larger model of each test (F). A fit that weighed its poses by the wander between them (generalised least
# squares, ``fit.means.channel_wander``) holds the scatter in that wander, sized under the baseline alone: an
# effect's own pattern would be taken for wander and tested against itself. The scatter is measured here again.

def _scalar_scatter(fit: OrientationFreeFit, start: np.ndarray, means: np.ndarray, cov: np.ndarray,
                    k: int) -> tuple[np.ndarray, float]:
    """Each pose's residual variance of its noise, and the excess scatter's (0 where none was estimated)."""
    if fit.residual_cov is None:
        assert fit.noise_var is not None
        return fit.noise_var, fit.excess_std**2
    mag, grad, _ = magnitude_and_gradient(start, means)
    noise_var = np.maximum(np.einsum("ki,kij,kj->k", grad, cov, grad), VARIANCE_FLOOR * fit.result.g_local**2)
    tau2 = excess_variance(mag - fit.result.g_local, noise_var, len(means) - k) if len(means) > k else 0.0
    return noise_var, tau2


def _vector_excess(means: np.ndarray, cov: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """The excess covariance of the poses about their ordinary least-squares fit (``fit.lsq.ols``)."""
    return ols(np.column_stack([reference, np.ones(len(means))]), means, cov).excess_cov
