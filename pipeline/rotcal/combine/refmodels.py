"""What positions of known reference determine: the nested models of the
reference fit and the choice between them.

With known references (labelled poses, jig ``gx, gy, gz``) each position's
mean is m_k = O + C ref_k (``poses.reference_fit``, Geist 2017 Eq. 19): C
(output units per g) holds the nine intrinsic parameters and the three
angles of the sensor frame's rotation relative to the references' frame,
12 linear parameters with O. Its nested model of orthogonal axes is

    C = D R,   D = diag(g s_u, g s_v, g s_w),   R orthogonal (three angles),

nine nonlinear parameters: the sensitivities, the offsets and the rotation.
rotcal fits it by Gauss-Newton on the rotation group (R <- R exp([delta]x)
each step), started from the polar decomposition of the 12-parameter C (its
orthogonal factor, and C's row lengths as D), on the residuals
e_k = m_k - O - C ref_k. Sigma_k is the noise of the pose mean, T the
excess scatter of the 12-parameter fit (``lsq.ols``: zero unless its
residuals show scatter beyond the noise; when the 12 parameters are not
determined, the same moment estimate from the orthogonal fit's own
residuals). Ordinary least squares weighs every position alike;
so does this fit, each channel by 1 / (mean_k Sigma_k + T)_ii. The
covariance is the sandwich G (Sigma_k + T) G', G = (J' W J)^-1 J' W, as
``ols``'s, with the degrees of freedom of the fit that estimated T; the
angles are 90 degrees exactly.

The choice is ``posemodels.f_test`` (q = 3, nu = 3 (n - 4)) between the
minima of one weighted sum of squares: S_12 the ordinary least-squares
minimum of the linear model (the minimum for weights common to all
positions), S_9 the orthogonal fit's; the scale known when T = 0, else
S_12 / nu.

Before either fit, the conditioning: when every reference lies within
``posemodels.MIN_CONE_DEG`` of one direction, offsets and sensitivities
along it cannot be told apart, and neither model is determined.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import polars as pl

from rotcal.combine.heldout import compare, press
from rotcal.combine.multiposition import VARIANCE_FLOOR, pose_arrays
from rotcal.combine.posemodels import MIN_CONE_DEG, SELECTION_LEVEL, ModelChoice, f_test, gravity_cone
from rotcal.combine.poses import OrthogonalReferenceFit, ReferenceFit, reference_fit, references
from rotcal.fit.lsq import CONDITION_LIMIT, excess_is_significant, psd_part
from rotcal.model.physics import CHANNELS
from rotcal.model.results import Failure, IntrinsicResult, whole_fit_input
from rotcal.noise.poses import PoseCovariance

MAX_ITERATIONS = 50
STEP_TOLERANCE = 1e-12  # of the relative sensitivity, angle (rad) and offset steps
MIN_POSITIONS = 4  # nine parameters and three residual degrees of freedom


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]x (..., 3, 3): [v]x w = v x w."""
    z = np.zeros(v.shape[:-1])
    x, y, w = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([np.stack([z, -w, y], -1), np.stack([w, z, -x], -1), np.stack([-y, x, z], -1)], -2)


def _rotation(delta: np.ndarray) -> np.ndarray:
    """exp([delta]x) (Rodrigues' formula)."""
    angle = float(np.linalg.norm(delta))
    k = _skew(delta / angle) if angle > 0 else np.zeros((3, 3))
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * k @ k


def _weights(cov: np.ndarray, excess: np.ndarray, scale: float) -> np.ndarray:
    """(3,) the channels' weights 1 / (mean_k Sigma_k + T)_ii, common to
    every position as ordinary least squares weighs them (a floor of
    ``VARIANCE_FLOOR`` scale^2 keeps noise-free simulated poses finite)."""
    return 1.0 / (np.diag(cov.mean(axis=0) + excess) + VARIANCE_FLOOR * scale**2)


def _residuals_and_jacobian(s: np.ndarray, rotation: np.ndarray, offsets: np.ndarray, ref: np.ndarray,
                            m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """e_k = m_k - O - D R ref_k (n, 3) and de_k/d(s, delta, O) (n, 3, 9),
    delta the rotation step R exp([delta]x): de/ddelta = D R [ref_k]x."""
    turned = ref @ rotation.T
    e = m - offsets - turned * s
    n = len(m)
    jac = np.zeros((n, 3, 9))
    jac[:, np.arange(3), np.arange(3)] = -turned
    jac[:, :, 3:6] = s[None, :, None] * (rotation[None] @ _skew(ref))
    jac[:, :, 6:] = -np.eye(3)
    return e, jac


def _gauss_newton(s: np.ndarray, rotation: np.ndarray, offsets: np.ndarray, ref: np.ndarray, m: np.ndarray,
                  root_w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, bool]:
    """The weighted least-squares minimum from (s, R, O), and whether the steps converged."""
    for _ in range(MAX_ITERATIONS):
        e, jac = _residuals_and_jacobian(s, rotation, offsets, ref, m)
        step = np.linalg.lstsq((jac * root_w[None, :, None]).reshape(-1, 9), -(e * root_w).ravel(), rcond=None)[0]
        s, rotation, offsets = s + step[:3], rotation @ _rotation(step[3:6]), offsets + step[6:]
        if max(np.abs(step[:3] / s).max(), np.abs(step[3:6]).max(), np.abs(step[6:]).max() / np.abs(s).max()) < STEP_TOLERANCE:
            return s, rotation, offsets, True
    return s, rotation, offsets, False


def _own_excess(e: np.ndarray, jac: np.ndarray, cov: np.ndarray, dof: int) -> np.ndarray:
    """T from the orthogonal fit's own residuals when the 12 parameters are
    not determined: ``ols``'s moment estimate, the leverage of a position
    the trace of its 3 x 3 block of the hat matrix over three."""
    ok = np.linalg.det(cov) > 0  # a summary's zero scatter: no known noise, any residual is excess
    chi2 = float(np.einsum("ki,kij,kj->", e[ok], np.linalg.inv(cov[ok]), e[ok])) if ok.all() else float("inf")
    if not excess_is_significant(chi2, dof):
        return np.zeros((3, 3))
    flat = jac.reshape(-1, 9)
    hat = flat @ np.linalg.pinv(flat)  # pinv: a singular fit is refused after this, not here
    leverage = np.einsum("kiki->k", hat.reshape(len(e), 3, len(e), 3)) / 3.0
    return psd_part((e.T @ e - np.einsum("k,kij->ij", 1.0 - leverage, cov)) / (dof / 3.0))


def orthogonal_reference_fit(poses: pl.DataFrame, g_local: float, g_uncertainty: float,
                             full: ReferenceFit | Failure | None = None,
                             misalignment_u: float = 0.0) -> OrthogonalReferenceFit | Failure:
    """The six intrinsic parameters of orthogonal axes (and R) from
    positions of known reference (module docstring); ``full`` the
    12-parameter fit when already made; ``misalignment_u`` the prior of the
    angles' cosines the model fixes (``_misalignment_prior``). A
    ``Failure`` with the reason when the positions do not determine them."""
    n = poses.height
    if n < MIN_POSITIONS:
        return Failure(0.0, f"{n} positions with a known reference: the orthogonal model's 9 parameters need at "
                            f"least {MIN_POSITIONS} (three residual degrees of freedom)")
    full = reference_fit(poses, g_local, g_uncertainty) if full is None else full
    m, cov = pose_arrays(poses)
    ref = references(poses)
    design = np.column_stack([ref, np.ones(n)])
    start = np.linalg.lstsq(design, m, rcond=None)[0]  # the 12-parameter least squares (minimum norm when undetermined)
    C, offsets = start[:3].T, start[3]
    u, _, vt = np.linalg.svd(C)
    rotation, s = u @ vt, np.linalg.norm(C, axis=1)  # polar decomposition C = P Q: Q, and C's row lengths
    scale = float(np.abs(m).max())
    own = isinstance(full, Failure)
    excess = full.excess_cov if isinstance(full, ReferenceFit) and not own else np.zeros((3, 3))
    for _ in range(2 if own else 1):  # with its own T: once with the noise, once more with T
        root_w = np.sqrt(_weights(cov, excess, scale))
        s, rotation, offsets, converged = _gauss_newton(s, rotation, offsets, ref, m, root_w)
        e, jac = _residuals_and_jacobian(s, rotation, offsets, ref, m)
        if own:
            excess = _own_excess(e, jac * root_w[None, :, None], cov, 3 * n - 9)
    wj = (jac * root_w[None, :, None]).reshape(-1, 9)
    finite = bool(np.all(np.isfinite(wj)) and np.all(np.linalg.norm(wj, axis=0) > 0))
    sv = np.linalg.svd(wj / np.linalg.norm(wj, axis=0), compute_uv=False) if finite else np.array([1.0, 0.0])
    condition = sv[0] / max(sv[-1], 1e-300)
    # each axis needs gravity along it in some pose: sin(elevation from the axis' perpendicular plane)
    excitation = np.abs(ref @ rotation.T).max(axis=0) / np.linalg.norm(ref, axis=1).max()
    idle = [CHANNELS[i] for i in np.flatnonzero(excitation < np.sin(np.radians(MIN_CONE_DEG)))]
    why = (f"its Jacobian's condition number is {condition:.2g}" if condition >= CONDITION_LIMIT
           else "its fit did not converge" if not converged
           else f"no pose has gravity within {90 - MIN_CONE_DEG:g} degrees of axis {', '.join(idle)}, so its sensitivity "
                "is not determined" if idle or np.any(s <= 0) else "")
    if why:
        return Failure(0.0, f"the references do not determine the orthogonal model's 9 parameters: {why}")
    # the sandwich G (Sigma_k + T) G', G = (J' W J)^-1 J' W: d(parameters)/d(position means)
    gain = np.linalg.solve(wj.T @ wj, wj.T).reshape(9, n, 3) * root_w
    params_cov = np.einsum("pki,kij,qkj->pq", gain, cov + excess[None], gain)
    prior_cov = _misalignment_prior(gain, s, rotation, ref, misalignment_u)
    # state (C rows, O) of the parameters (s, delta, O): dC_ij/ds_i = R_ij, dC/ddelta_j = D R [e_j]x
    lift = np.zeros((12, 9))
    for i in range(3):
        lift[3 * i: 3 * i + 3, i] = rotation[i]
        lift[:9, 3 + i] = (s[:, None] * (rotation @ _skew(np.eye(3)[i]))).ravel()
    lift[9:, 6:] = np.eye(3)
    state_cov = lift @ params_cov @ lift.T
    state = np.concatenate([(s[:, None] * rotation).ravel(), offsets])
    dof = 3 * n - 9
    # the scatter's degrees of freedom: those of the fit that estimated T (the 12-parameter one, as its own result
    # states; its own where that one is exact and estimated none)
    parts = [(whole_fit_input("positions", float(full.dof if isinstance(full, ReferenceFit) and full.dof else dof)), state_cov)]
    if misalignment_u > 0:
        parts.append((whole_fit_input("misalignment prior", float("inf")), lift @ prior_cov @ lift.T))
    result = IntrinsicResult.from_state(0.0, state, sum(p for _, p in parts), g_local, g_uncertainty, parts)
    result = _orthogonal_angles(result)
    return OrthogonalReferenceFit(result, rotation, e, dof, excess, root_w**2)


def _misalignment_prior(gain: np.ndarray, s: np.ndarray, rotation: np.ndarray, ref: np.ndarray,
                        misalignment_u: float) -> np.ndarray:
    """(9, 9) the covariance the fixed angles lend the fitted parameters, a
    Type B input (GUM 4.3) as ``multiposition.orientation_free`` takes
    one: axis b's row of C tilted towards axis a's by cos(phi_ab) moves
    position k's mean by s_b (r_a . ref_k) along b, and the fit passes that
    on through its gain. Where the positions tell a tilt from a change of
    offset or sensitivity (the faces) the term vanishes; where they lie near
    one circle it dominates, as the model's assumption then decides the
    values."""
    if misalignment_u <= 0:
        return np.zeros((9, 9))
    shift = np.zeros((len(ref), 3, 3))  # d(mean_k)/d(cos phi_ab), the pairs uv, vw, wu
    for pair, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        shift[:, b, pair] = s[b] * (ref @ rotation[a])
    sensitivity = np.einsum("pki,kic->pc", gain, shift) * misalignment_u
    return sensitivity @ sensitivity.T


def _orthogonal_angles(result: IntrinsicResult) -> IntrinsicResult:
    """The result with its angles exactly 90 degrees and certain: the model
    fixes them (rounding leaves the rows orthogonal to 1e-16 only)."""
    value, cov = result.value.copy(), result.cov.copy()
    value[3:6] = 90.0
    cov[3:6, :] = cov[:, 3:6] = 0.0
    budget = {label: np.where(np.arange(9) // 3 == 1, 0.0, part) for label, part in result.budget.items()}
    return replace(result, value=value, cov=cov, budget=budget)


def choose_reference_model(poses: pl.DataFrame, g_local: float, g_uncertainty: float,
                           misalignment_u: float = 0.0, between: PoseCovariance | None = None) -> ModelChoice | Failure:
    """Both models fitted to positions of known reference and the one the
    evidence chooses (the orthogonal one with the angles' prior
    ``misalignment_u``); a ``Failure`` when the references lie within
    ``MIN_CONE_DEG`` of one direction (neither model determined);
    ``between``: the pose means' covariance between poses (``noise.poses``),
    the 12-parameter fit then generalised least squares."""
    cone = gravity_cone(references(poses))
    if cone is not None:
        return Failure(0.0, cone)
    full = reference_fit(poses, g_local, g_uncertainty, between)
    orthogonal = orthogonal_reference_fit(poses, g_local, g_uncertainty, full, misalignment_u)
    if isinstance(full, Failure) or isinstance(orthogonal, Failure):
        return ModelChoice(full, orthogonal, "orthogonal" if isinstance(full, Failure) else "baseline")
    s_full = float(np.sum(full.residuals**2 * orthogonal.weights))  # ordinary least squares: the minimum for these weights too
    known = not np.any(full.excess_cov)
    f, p, dof = f_test(orthogonal.sum_sq - s_full, 3, 1.0 if known else s_full / full.dof,
                       float("inf") if known else float(full.dof))
    if not full.dof:  # an exact 12-parameter fit predicts no position left out (each its own leverage 1)
        return ModelChoice(full, orthogonal, "baseline" if p < SELECTION_LEVEL else "orthogonal", f, p, dof)
    held = compare(_held_out_orthogonal(orthogonal, poses), _held_out_full(full, poses, orthogonal.weights))
    return ModelChoice(full, orthogonal, "baseline" if p < SELECTION_LEVEL and held.better else "orthogonal", f, p, dof, held)


def _held_out_full(full: ReferenceFit, poses: pl.DataFrame, weights: np.ndarray) -> np.ndarray:
    """Each position's squared leave-one-out prediction error under the
    12-parameter fit (one design for every channel: e_k / (1 - h_kk))."""
    design = np.column_stack([references(poses), np.ones(poses.height)])
    return press((full.residuals * np.sqrt(weights)).ravel(), np.kron(design, np.eye(3)) * np.tile(np.sqrt(weights), len(design))[:, None], 3)


def _held_out_orthogonal(fit: OrthogonalReferenceFit, poses: pl.DataFrame) -> np.ndarray:
    """Each position's squared leave-one-out prediction error under the orthogonal fit."""
    s = np.linalg.norm(fit.result.state[:9].reshape(3, 3), axis=1)  # the rows of C = D R: output per g
    e, jac = _residuals_and_jacobian(s, fit.rotation, fit.result.state[9:], references(poses), pose_arrays(poses)[0])
    root_w = np.sqrt(fit.weights)
    return press((e * root_w).ravel(), (jac * root_w[None, :, None]).reshape(-1, 9), 3)



def reference_advice(ref: np.ndarray) -> list[str]:
    """Why the angles rest on the orthogonal model when the references lie
    in one plane (the 12 parameters undetermined), and the pose that
    determines them: gravity along the plane's normal. (With references
    spanning three dimensions every angle is determined, best by the faces:
    pose +u measures r_v's u component, the cross-axis reading, with
    weight 1, a pose between +u and +v with weight 0.71.)"""
    spread = np.linalg.svd(np.column_stack([ref, np.ones(len(ref))]), compute_uv=False)
    if len(ref) >= 4 and spread[-1] > 1e-9 * spread[0]:
        return []  # the references span three dimensions: the 12 parameters failed for another reason
    normal = np.linalg.svd(ref)[2][-1]
    normal = normal * np.sign(normal[np.argmax(np.abs(normal))])
    axis = ", ".join(f"{c:.2f}" for c in normal + 0.0)
    return [f"the references lie in one plane (normal ({axis}) in the references' frame): they do not determine the 12 "
            "parameters, and the orthogonal model takes every angle as 90 degrees; a pose with gravity along that normal "
            "(up or down) determines phi_uv, phi_vw and phi_wu, and the sensitivity of an axis near it"]
