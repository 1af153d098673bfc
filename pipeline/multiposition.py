"""Static multi-position calibration without known orientations.

In every static pose the DUT measures gravity alone, so the corrected
acceleration a_k = R^-1 (m_k - O) has the magnitude g_local whatever the pose
(the condition imu_tk and ArduPilot use). R (rows r_u, r_v, r_w) is fixed
by it only up to a common rotation, which the intrinsic parameters do not
see (Geist 2017 section 1): rotcal writes R = L Q with L lower triangular
(u along x, v in the x-y plane) and fits the six elements of L and the three
offsets, exactly the nine intrinsic parameters.

Each pose's residual is (|a_k| - g) divided by its standard uncertainty from
the covariance of the pose mean, so the fit is weighted least squares; the
parameter covariance is scaled by the reduced chi-square when the poses
scatter more than their noise says (hand-placed poses rarely rest
perfectly), so the uncertainty covers what the noise alone does not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from scipy.optimize import least_squares

from pipeline.combine import IntrinsicResult, intrinsic_jacobian
from pipeline.physics import CHANNELS

TRIL = np.tril_indices(3)  # (0,0) (1,0) (1,1) (2,0) (2,1) (2,2)


@dataclass(frozen=True)
class PoseFailure:
    reason: str


@dataclass(frozen=True, eq=False)
class OrientationFreeFit:
    """The fit behind an orientation-free result: per-pose |a| after
    correction, the reduced chi-square and the degrees of freedom."""

    result: IntrinsicResult
    magnitude: np.ndarray
    chi2_reduced: float
    dof: int


def pose_table(t_ns: np.ndarray, y: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> pl.DataFrame:
    """Mean and covariance of the mean of each pose (samples ``starts[k]:stops[k]``)."""
    rows = []
    for k, (a, b) in enumerate(zip(starts, stops)):
        part = y[a:b]
        cov = np.cov(part.T, ddof=1) / part.shape[0]
        rows.append({"pose": k, "t_start_ns": int(t_ns[a]), "t_end_ns": int(t_ns[b - 1]), "n_samples": int(b - a),
                     **{f"mean_{c}": float(part[:, r].mean()) for r, c in enumerate(CHANNELS)},
                     "cov_mean": cov.ravel().tolist()})
    return pl.DataFrame(rows, schema_overrides={"cov_mean": pl.List(pl.Float64)})


def _ellipsoid_start(m: np.ndarray, g: float) -> np.ndarray:
    """Algebraic ellipsoid fit (m - O)' S (m - O) = g^2 as a starting point."""
    x, y, z = m.T
    design = np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, 2 * x, 2 * y, 2 * z])
    coef = np.linalg.lstsq(design, np.ones(len(m)), rcond=None)[0]
    A = np.array([[coef[0], coef[3], coef[4]], [coef[3], coef[1], coef[5]], [coef[4], coef[5], coef[2]]])
    offset = -np.linalg.solve(A, coef[6:])
    unit_quadric = A / (1.0 + offset @ A @ offset)  # (m - O)' Q (m - O) = 1
    L = np.linalg.cholesky(np.linalg.inv(unit_quadric) / g**2)  # L L' = (g^2 Q)^-1
    return np.concatenate([L[TRIL], offset])


def _residuals(params: np.ndarray, m: np.ndarray, cov: np.ndarray, g: float) -> np.ndarray:
    L = np.zeros((3, 3))
    L[TRIL] = params[:6]
    a = np.linalg.solve(L, (m - params[6:]).T).T
    mag = np.linalg.norm(a, axis=1)
    # d|a|/dm = a_hat' L^-1: the noise of the pose mean projected on |a|
    grad = np.linalg.solve(L.T, (a / mag[:, None]).T).T
    sigma = np.sqrt(np.einsum("ki,kij,kj->k", grad, cov, grad))
    return (mag - g) / sigma


def orientation_free(poses: pl.DataFrame, g_local: float, g_uncertainty: float,
                     min_poses: int = 12) -> OrientationFreeFit | PoseFailure:
    """The nine intrinsic parameters from static poses of unknown orientation."""
    n = poses.height
    if n < min_poses:
        return PoseFailure(f"{n} static poses: at least {min_poses} are needed to identify the nine "
                           "intrinsic parameters with residual degrees of freedom")
    m = poses.select(f"mean_{c}" for c in CHANNELS).to_numpy()
    cov = np.array(poses["cov_mean"].to_list()).reshape(n, 3, 3)
    # a floor of one output quantum's variance keeps perfectly quiet poses finite
    cov = cov + np.eye(3)[None] * (1.0 / 12.0) / poses["n_samples"].to_numpy()[:, None, None]
    try:
        start = _ellipsoid_start(m, g_local)
    except np.linalg.LinAlgError:
        return PoseFailure("the poses are too alike to identify the nine intrinsic parameters "
                           "(their means do not span an ellipsoid)")
    fit = least_squares(_residuals, start, args=(m, cov, g_local), method="lm", x_scale="jac")
    jac = fit.jac
    sv = np.linalg.svd(jac, compute_uv=False)
    if sv[-1] <= sv[0] * 1e-9:
        return PoseFailure(f"the poses are too alike to identify the nine intrinsic parameters "
                           f"(condition number {sv[0] / max(sv[-1], 1e-300):.2g})")
    dof = n - 9
    chi2_reduced = float(fit.fun @ fit.fun / dof)
    params_cov = np.linalg.inv(jac.T @ jac) * max(chi2_reduced, 1.0)
    # state = g * rows of L (the g-free coefficient space of combine) and O
    lift = np.zeros((12, 9))
    for k, (i, j) in enumerate(zip(*TRIL)):
        lift[3 * i + j, k] = g_local
    lift[9:, 6:] = np.eye(3)
    L = np.zeros((3, 3))
    L[TRIL] = fit.x[:6]
    state = np.concatenate([(g_local * L).ravel(), fit.x[6:]])
    state_cov = lift @ params_cov @ lift.T
    value, jac_state, jac_g = intrinsic_jacobian(state, g_local)
    noise = np.einsum("ij,jk,ik->i", jac_state, state_cov, jac_state)
    g_part = (jac_g * g_uncertainty) ** 2
    result = IntrinsicResult(
        rate_hz=0.0, value=value,
        cov=jac_state @ state_cov @ jac_state.T + np.outer(jac_g, jac_g) * g_uncertainty**2,
        state=state, state_cov=state_cov, budget={"pose noise": noise, "g_local": g_part}, g_local=g_local,
    )
    magnitude = np.linalg.norm(np.linalg.solve(L, (m - fit.x[6:]).T).T, axis=1)
    return OrientationFreeFit(result, magnitude, chi2_reduced, dof)
