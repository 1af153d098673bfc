"""Static multi-position calibration without known orientations.

In every static pose the DUT measures gravity alone, so the corrected
acceleration a_k = R^-1 (m_k - O) has the magnitude g_local whatever the pose
(the condition imu_tk and ArduPilot use). R (rows r_u, r_v, r_w) is fixed
by it only up to a common rotation, which the intrinsic parameters do not
see (Geist 2017 section 1): rotcal writes R = L Q with L lower triangular
(u along x, v in the x-y plane: the *intrinsic frame*) and fits the six
elements of L and the three offsets, exactly the nine intrinsic parameters.

Each pose's residual is |a_k| - g, weighted by its variance: the noise of
the pose mean projected on |a| (d|a|/dm = a_hat' L^-1) plus an excess
variance tau^2 common to all poses, estimated so that the weighted residuals
have a reduced chi-square of one when the poses scatter more than their
noise says (chi-square beyond its 99th percentile, ``lsq.excess_is_significant``;
Paule and Mandel's random-effects estimate; hand-placed poses
rarely rest perfectly, and the mean of a long rest is limited by
low-frequency noise rather than by 1/sqrt(n)). With tau^2 = 0 this is
weighted least squares; the covariance of the nine parameters is
(J' W J)^-1 at the solution, split into the share of the pose noise and of
the excess scatter.

The same fit with the three angles fixed at 90 degrees (``ORTHOGONAL``: L
diagonal, six parameters) is the nested model of orthogonal axes
(``combine.posemodels`` chooses between the two).

A model is determined when the poses outnumber its parameters (one residual
degree of freedom at least, to judge the scatter) and their gravity
directions do not all lie near one circle on the sphere (one rotation axis,
or a cone): points on a conic lie on a family of ellipsoids.
``direction_spread`` is the smallest singular value of the normalised
quadric design of the directions (the model's columns of it); below
``MIN_SPREAD`` rotcal refuses instead of reporting a meaningless fit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.fit.lsq import excess_is_significant, nonlinear
from rotcal.fit.means import scalar_wander
from rotcal.model.physics import CHANNELS
from rotcal.model.results import Failure, IntrinsicResult, whole_fit_input
from rotcal.noise.poses import PoseCovariance

TRIL = np.tril_indices(3)  # (0,0) (1,0) (1,1) (2,0) (2,1) (2,2)
MIN_SPREAD = 1e-3  # below it the directions are degenerate to within noise; weaker geometry shows in u
MAX_ITERATIONS = 30
VARIANCE_FLOOR = 1e-24  # relative to g^2: keeps noise-free (simulated) poses finite
# the free elements of (L[TRIL], O) per model: every one, or L's diagonal and O (the axes orthogonal)
FULL = np.arange(9)
ORTHOGONAL = np.array([0, 2, 5, 6, 7, 8])
TOO_ALIKE = ("the poses are too alike to identify the {k} intrinsic parameters: their gravity directions lie "
             "near one circle on the sphere (one rotation axis, or a cone){detail}; add poses turned about another axis")


@dataclass(frozen=True, eq=False)
class OrientationFreeFit:
    """The fit behind an orientation-free result: per-pose |a| after
    correction (m/s^2), the reduced chi-square of the noise-only weights,
    the degrees of freedom, the excess scatter tau (m/s^2, per pose) and the
    spread of the pose directions."""

    result: IntrinsicResult
    magnitude: np.ndarray
    chi2_reduced: float
    dof: int
    excess_std: float = 0.0
    direction_spread: float = float("nan")
    noise_var: np.ndarray | None = None
    residual_cov: np.ndarray | None = None  # generalised least squares: the residuals' covariance between poses

    @property
    def parameters(self) -> int:
        return len(self.magnitude) - self.dof

    @property
    def variance(self) -> np.ndarray:
        """Each pose's residual variance in the fit: noise and excess scatter ((m/s^2)^2)."""
        assert self.noise_var is not None
        return self.noise_var + self.excess_std**2


def pose_arrays(poses: pl.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """Pose means (n, 3) and covariances of the means (n, 3, 3)."""
    m = poses.select(f"mean_{c}" for c in CHANNELS).to_numpy()
    cov = np.array(poses["cov_mean"].to_list(), float).reshape(poses.height, 3, 3)
    return m, cov


def _ellipsoid_start(m: np.ndarray, g: float, free: np.ndarray = FULL) -> np.ndarray:
    """Algebraic ellipsoid fit (m - O)' S (m - O) = g^2 as a starting point
    (axis-aligned, S diagonal, for the orthogonal model)."""
    centre = m.mean(axis=0)
    span = np.abs(m - centre).max()
    x, y, z = ((m - centre) / span).T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z])
    coef = np.zeros(9)
    columns = FULL if len(free) == 9 else np.array([0, 1, 2, 6, 7, 8])  # S's diagonal and the linear terms
    coef[columns] = np.linalg.lstsq(design[:, columns], np.ones(len(m)), rcond=None)[0]
    A = np.array([[coef[0], coef[3], coef[4]], [coef[3], coef[1], coef[5]], [coef[4], coef[5], coef[2]]])
    offset = -np.linalg.solve(A, coef[6:])
    unit_quadric = A / (1.0 + offset @ A @ offset)  # (m - O)' Q (m - O) = 1, scaled coordinates
    L = np.linalg.cholesky(np.linalg.inv(unit_quadric) / g**2) * span  # L L' = (g^2 Q)^-1
    return np.concatenate([L[TRIL], centre + span * offset])


def _lower(params: np.ndarray) -> np.ndarray:
    L = np.zeros((3, 3))
    L[TRIL] = params[:6]
    return L


def magnitude_and_gradient(params: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """|a_k|, d|a_k|/dm_k = a_hat' L^-1 (n, 3) and d|a_k|/dparams (n, 9)."""
    L = _lower(params)
    a = np.linalg.solve(L, (m - params[6:]).T).T
    mag = np.linalg.norm(a, axis=1)
    grad = np.linalg.solve(L.T, (a / mag[:, None]).T).T
    rows, cols = TRIL
    jac = np.hstack([-grad[:, rows] * a[:, cols], -grad])  # dL_ij: -grad_i a_j; dO_i: -grad_i
    return mag, grad, jac


def angle_cosines(params: np.ndarray) -> np.ndarray:
    """cos(phi_uv), cos(phi_vw), cos(phi_wu) of the rows of L."""
    rows = _lower(params)
    unit = rows / np.linalg.norm(rows, axis=1)[:, None]
    return np.array([unit[i] @ unit[j] for i, j in ((0, 1), (1, 2), (2, 0))])


def _cosine_jacobian(params: np.ndarray) -> np.ndarray:
    """d cos(phi) / d params (3, 9), by central differences (a 3 x 9 Jacobian of a closed form)."""
    step = 1e-7 * np.maximum(np.abs(params[:6]).max(), 1e-300)
    jac = np.zeros((3, 9))
    for j in range(6):
        dp = np.zeros(9)
        dp[j] = step
        jac[:, j] = (angle_cosines(params + dp) - angle_cosines(params - dp)) / (2 * step)
    return jac


def _solve(start: np.ndarray, m: np.ndarray, g: float, sigma: np.ndarray, free: np.ndarray,
           prior_u: float = 0.0) -> np.ndarray:
    """Weighted least squares of (|a_k| - g) / sigma_k with fixed weights,
    over the ``free`` parameters (the others stay as in ``start``); with
    ``prior_u`` > 0, the angles' cosines as three observations of 0 with
    that standard uncertainty (the datasheet's prior). ``sigma`` (n, n):
    the lower Cholesky factor of the residuals' covariance, generalised
    least squares (the residuals whitened by it)."""
    from scipy.linalg import solve_triangular  # here: scipy's import would slow every CLI start

    def white(r: np.ndarray) -> np.ndarray:
        return solve_triangular(sigma, r, lower=True) if sigma.ndim == 2 else (r.T / sigma).T

    def whole(p: np.ndarray) -> np.ndarray:
        params = start.copy()
        params[free] = p
        return params

    def residuals(p: np.ndarray) -> np.ndarray:
        r = white(magnitude_and_gradient(whole(p), m)[0] - g)
        return np.concatenate([r, angle_cosines(whole(p)) / prior_u]) if prior_u else r

    def jacobian(p: np.ndarray) -> np.ndarray:
        j = white(magnitude_and_gradient(whole(p), m)[2][:, free])
        return np.vstack([j, _cosine_jacobian(whole(p))[:, free] / prior_u]) if prior_u else j

    return whole(nonlinear(residuals, jacobian, start[free]).x)


def excess_variance(residuals: np.ndarray, noise_var: np.ndarray, dof: int) -> float:
    """tau^2 >= 0 with sum r^2 / (v + tau^2) = dof (Paule and Mandel), or 0
    when the noise alone explains the residuals (``excess_is_significant``)."""
    from scipy.optimize import brentq  # here: scipy's import would slow every CLI start

    def chi2(tau2: float) -> float:
        return float(np.sum(residuals**2 / (noise_var + tau2))) - dof

    if not excess_is_significant(chi2(0.0) + dof, dof):
        return 0.0
    upper = float(np.sum(residuals**2)) / dof
    return brentq(chi2, 0.0, upper + 1e-300, xtol=1e-14 * upper, rtol=1e-12)


def direction_spread(directions: np.ndarray, free: np.ndarray = FULL) -> float:
    """Smallest singular value of the quadric design of unit directions
    (d_i d_j, d_i; the columns of the ``free`` parameters), divided by
    sqrt(n): zero when they lie on one circle."""
    d = directions
    rows, cols = TRIL
    design = np.hstack([d[:, rows] * d[:, cols], d])[:, free]
    if len(d) < design.shape[1]:
        return 0.0
    return float(np.linalg.svd(design, compute_uv=False)[-1] / np.sqrt(len(d)))


def _generalised(params: np.ndarray, m: np.ndarray, g: float, free: np.ndarray, prior: float,
                 between: PoseCovariance) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Generalised least squares of |a_k| - g under the pose means'
    covariance between poses (``noise.poses``) with the wander their
    scatter shows beyond it (``noise.poses.scalar_wander``), from the
    weighted fit's ``params``: (params, the residuals' covariance under
    the noise model, and with the wander); None where that covariance is
    the poses' own alone and their scatter shows no wander (the weighted
    fit as it was)."""
    floor = VARIANCE_FLOOR * g**2 * np.eye(len(m))
    mag, grad, jac = magnitude_and_gradient(params, m)
    if between.plain and scalar_wander(between, mag - g, grad, jac[:, free]) is between:
        return None
    wandering = between
    for _ in range(3):  # the wander from the residuals, the fit with it: the residuals move little
        wandering = scalar_wander(between, mag - g, grad, jac[:, free])
        params = _solve(params, m, g, np.linalg.cholesky(wandering.projected(grad) + floor), free, prior)
        mag, grad, jac = magnitude_and_gradient(params, m)
    return params, between.projected(grad) + floor, wandering.projected(grad) + floor


def orientation_free(poses: pl.DataFrame, g_local: float, g_uncertainty: float,
                     free: np.ndarray = FULL, misalignment_u: float = 0.0,
                     between: PoseCovariance | None = None) -> OrientationFreeFit | Failure:
    """The nine intrinsic parameters from static poses of unknown orientation
    (``free = ORTHOGONAL``: the six of orthogonal axes, the angles 90 degrees;
    ``misalignment_u`` > 0: the standard uncertainty of the angles' cosines
    from the datasheet, ``combine.placement``: a Type B input carried into
    the six where the model fixes the angles; three prior observations
    cos(phi) = 0 where it fits them, so that an angle the poses barely
    determine rests on the datasheet, not on the poses' small tilts).

    ``poses`` holds ``mean_u, mean_v, mean_w`` and ``cov_mean`` (as from
    ``fit.means.pose_table``). ``between``: the pose means' covariance
    between poses (``fit.means.modelled_pose_table``), the residuals then
    weighed by generalised least squares with it and the wander their
    scatter shows (the offsets carry the wander all poses share). Returns
    a ``Failure`` (rate 0) with the reason when the poses are too few or
    too alike to identify the model's parameters.
    """
    n, k = poses.height, len(free)
    # the orthogonal model may be exactly determined (the six faces): its angles' prior and the pose noise give its u
    needed = k if len(free) < len(FULL) else k + 1
    if n < needed:
        return Failure(0.0, f"{n} static poses: the {k}-parameter model needs at least {needed} (its {k} intrinsic "
                            f"parameters{' and one residual degree of freedom' if needed > k else ''})")
    m, cov = pose_arrays(poses)
    if n == k and not np.any(cov):
        return Failure(0.0, f"{n} pose means without scatter determine the {k} parameters exactly, leaving no residual to "
                            "estimate their uncertainty from: give each pose's standard deviation and count (pose "
                            "summaries, docs/inputs.md), or more poses")
    try:
        params = _ellipsoid_start(m, g_local, free)
    except np.linalg.LinAlgError:
        return Failure(0.0, TOO_ALIKE.format(k=k, detail=": their means do not span an ellipsoid"))
    dof = n - k
    tau2 = 0.0
    floor = VARIANCE_FLOOR * g_local**2
    prior = misalignment_u if len(free) == len(FULL) else 0.0  # the angles fitted: their prior as observations
    for _ in range(MAX_ITERATIONS):
        mag, grad, _ = magnitude_and_gradient(params, m)
        noise_var = np.maximum(np.einsum("ki,kij,kj->k", grad, cov, grad), floor)
        params = _solve(params, m, g_local, np.sqrt(noise_var + tau2), free, prior)
        mag, grad, jac = magnitude_and_gradient(params, m)
        noise_var = np.maximum(np.einsum("ki,kij,kj->k", grad, cov, grad), floor)
        new = excess_variance(mag - g_local, noise_var, dof)
        converged = abs(new - tau2) <= 1e-9 * (new + np.median(noise_var))
        tau2 = new
        if converged:
            break
    model_cov = residual_cov = None
    generalised = _generalised(params, m, g_local, free, prior, between) \
        if between is not None and dof > 0 and np.all(np.isfinite(params)) else None
    if generalised is not None:
        params, model_cov, residual_cov = generalised
        mag, grad, jac = magnitude_and_gradient(params, m)
        noise_var, tau2 = np.diag(residual_cov).copy(), 0.0
    L = _lower(params)
    if not np.all(np.isfinite(params)) or np.any(np.diag(L) <= 0):
        return Failure(0.0, "the orientation-free fit did not converge to a valid responsivity matrix")
    a = np.linalg.solve(L, (m - params[6:]).T).T
    spread = direction_spread(a / np.linalg.norm(a, axis=1)[:, None], free)
    if spread < MIN_SPREAD:
        return Failure(0.0, TOO_ALIKE.format(k=k, detail=f" (direction spread {spread:.3g} < {MIN_SPREAD})"))
    resid = mag - g_local
    chi2_reduced = (float(np.sum(resid**2 / noise_var) if model_cov is None else resid @ np.linalg.solve(model_cov, resid))
                    / dof if dof else float("nan"))
    full_jac = jac
    jac = jac[:, free]
    cosines = _cosine_jacobian(params)[:, free] / prior if prior else np.zeros((0, len(free)))
    # the residuals weighed by the inverse of their covariance: diagonal, unless generalised
    weighed = jac * (1.0 / (noise_var + tau2))[:, None] if residual_cov is None else np.linalg.solve(residual_cov, jac)
    params_cov = np.linalg.inv(jac.T @ weighed + cosines.T @ cosines)
    gain = params_cov @ weighed.T  # (k, n): d params / d residual
    # state = g * rows of L (the g-free coefficient space of combine) and O
    lift = np.zeros((12, 9))
    for j, (r, c) in enumerate(zip(*TRIL)):
        lift[3 * r + c, j] = g_local
    lift[9:, 6:] = np.eye(3)
    lift = lift[:, free]
    gain = lift @ gain
    # the pose means' noise is known from many samples each; the excess scatter is estimated from the dof residuals
    if residual_cov is None:
        parts = [(whole_fit_input("pose noise", float("inf")), (gain * noise_var) @ gain.T)]
    else:  # the noise model's covariance, and the wander the residuals' scatter measures beyond it
        assert model_cov is not None
        parts = [(whole_fit_input("pose noise", float("inf")), gain @ model_cov @ gain.T),
                 (whole_fit_input("pose wander", float(dof)), gain @ (residual_cov - model_cov) @ gain.T)]
    if dof and residual_cov is None:  # an exactly determined fit has no residual to estimate the scatter from
        parts.append((whole_fit_input("excess scatter", float(dof)), (gain * tau2) @ gain.T))
    if prior:  # the datasheet's prior of the angles, a Type B input (GUM 4.3)
        prior_gain = lift @ params_cov @ cosines.T
        parts.append((whole_fit_input("misalignment prior", float("inf")), prior_gain @ prior_gain.T))
    fixed = np.setdiff1d(FULL[:6], free)
    if misalignment_u > 0 and fixed.size:
        # the angles the model fixes at 90 degrees, a Type B input (GUM 4.3): L_ij = L_ii cos(phi) within its prior
        prior = misalignment_u * np.abs(np.diag(L))[TRIL[0][fixed]]
        sensitivity = gain @ full_jac[:, fixed] * prior
        parts.append((whole_fit_input("misalignment prior", float("inf")), sensitivity @ sensitivity.T))
    state = np.concatenate([(g_local * L).ravel(), params[6:]])
    result = IntrinsicResult.from_state(0.0, state, sum(p for _, p in parts), g_local, g_uncertainty, parts)
    return OrientationFreeFit(result, mag, chi2_reduced, dof, float(np.sqrt(tau2)), spread, noise_var, residual_cov)
