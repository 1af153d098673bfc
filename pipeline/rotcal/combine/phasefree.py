"""Intrinsic parameters of one rate from rotation segments without a phase
reference (docs/conventions.md: a segment without angle_deg has an unknown
theta0).

A segment about axis s fitted against its own phase phi (theta = theta_k +-
phi) gives, per channel r, the in-plane vector p_r = (-A_r, B_r) of the
responsivity components (g r_a, g r_b) of Geist 2017 Eq. 5 turned by the
unknown angle theta_k, and reflected when the rotation's sense is the
opposite of the phase's:

    C_r = O_r,
    A_r = -(sigma_k rho_ra cos theta_k + rho_rb sin theta_k),
    B_r = -sigma_k rho_ra sin theta_k + rho_rb cos theta_k,

with rho = g r (output units), (a, b) the components of Geist's Eq. 5 for
axis s and sigma_k = +-1. Each component of each vector is seen by two axes
and each offset by three, so the angles are fixed by the requirement that the
components measured twice agree: a joint weighted least-squares fit
of the twelve state elements (rho, O) and every segment's
theta_k to all segments' coefficient vectors. The weights are each
coefficient's inverse variance, as combine gives the labelled segments (Geist
2017 Eqs. 10 and 12), solved by ``rotcal.fit.lsq.nonlinear``; the covariance of the estimate is propagated from every
segment's full 9 x 9 covariance through the fit's linear response (a sandwich
estimate), so the estimated angles' uncertainty is in it. To first order the
intrinsic parameters do not depend on the angles at all (lengths and dot
products of turned vectors), which is why they match the labelled reduction
of the same data.

There is no continuous gauge freedom: a change of one segment's angle mixes
two columns of rho that the other two axes see separately. What stays free
is the sign of each table axis (a rotation or reflection of the whole
solution), which the intrinsic parameters do not see; rotcal fixes them by
the DUT's rough alignment (the diagonal of rho positive), so that rho is in
the table frame as the blind axis names are.

Segments that do have a table angle enter with theta_k = 0 and sigma_k = +1
fixed, and then also fix the signs of the axes.

The start values are closed-form: with G = rho rho^T = (1/2) sum_k P_k P_k^T
over one segment per axis, P_k^T G^-1 P_l is the outer product of the shared
axis's direction in segment k's and segment l's phase frames, whose singular
vectors give every segment's turn and reflection.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotcal.combine.labelled import STATE, segment_input
from rotcal.fit.lsq import nonlinear
from rotcal.model.physics import AXES, COS_COMPONENT, SIN_COMPONENT, axis_index
from rotcal.model.results import Failure, IntrinsicResult


@dataclass(frozen=True, eq=False)
class PhaseSegment:
    """One rotation segment's coefficient vector (channel-major C, A, B),
    its 9 x 9 covariance, its table axis, whether its phase is the table
    angle (``fixed``) or its own, and its fit's residual degrees of freedom
    (0: the noise treated as known)."""

    segment: int
    axis: str
    coef: np.ndarray
    cov: np.ndarray
    fixed: bool = False
    dof: int = 0


@dataclass(frozen=True, eq=False)
class PhaseFreeFit:
    """The result and the solved phase offsets (deg; NaN for fixed
    segments), their standard uncertainties, which segments turned the
    other way, and the fit's chi-square and degrees of freedom."""

    result: IntrinsicResult
    theta_deg: np.ndarray
    theta_u_deg: np.ndarray
    reflected: np.ndarray
    chi2: float
    dof: int


def _plane(axis: str) -> tuple[int, int]:
    s = axis_index(axis)
    return int(SIN_COMPONENT[s]), int(COS_COMPONENT[s])


def _in_plane(coef: np.ndarray) -> np.ndarray:
    """Rows p_r = (-A_r, B_r)."""
    c = coef.reshape(3, 3)
    return np.column_stack([-c[:, 1], c[:, 2]])


def _polar(m: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(m)
    return u @ vt


def _turn(q: np.ndarray) -> tuple[float, float]:
    """(theta, sigma) with q = diag(sigma, 1) Rot(theta)."""
    sigma = 1.0 if np.linalg.det(q) > 0 else -1.0
    rot = np.diag([sigma, 1.0]) @ q
    return float(np.arctan2(rot[1, 0], rot[0, 0])), sigma


def _start(segments: list[PhaseSegment]) -> np.ndarray:
    """Closed-form rho (3 x 3) from one segment per axis (module docstring)."""
    rep: dict[str, np.ndarray] = {}
    for seg in segments:
        rep.setdefault(seg.axis, _in_plane(seg.coef))
    gram_inv = np.linalg.inv(0.5 * sum(p @ p.T for p in rep.values()))
    q = {axis: np.zeros((2, 2)) for axis in rep}  # columns: the plane's axes in the segment's phase frame
    for i, k in enumerate(AXES):
        for m in AXES[i + 1 :]:
            shared = ({*_plane(k)} & {*_plane(m)}).pop()
            u, _, vt = np.linalg.svd(rep[k].T @ gram_inv @ rep[m])
            q[k][:, _plane(k).index(shared)] = u[:, 0]
            q[m][:, _plane(m).index(shared)] = vt[0]
    rho = np.zeros((3, 3))
    for axis, p in rep.items():
        a, b = _plane(axis)
        part = p @ _polar(q[axis])  # rho E = P Q^T, Q^T = q
        rho[:, a] += 0.5 * part[:, 0]
        rho[:, b] += 0.5 * part[:, 1]
    return rho


def _model(rho: np.ndarray, offset: np.ndarray, axis: str, theta: float, sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A segment's predicted coefficients and their derivatives with respect
    to rho (9 x 9), the offsets (9 x 3) and theta (9)."""
    a, b = _plane(axis)
    c, s = np.cos(theta), np.sin(theta)
    pred = np.zeros((3, 3))
    pred[:, 0] = offset
    pred[:, 1] = -(sigma * rho[:, a] * c + rho[:, b] * s)
    pred[:, 2] = -sigma * rho[:, a] * s + rho[:, b] * c
    d_rho = np.zeros((9, 9))
    d_off = np.zeros((9, 3))
    d_theta = np.zeros(9)
    for r in range(3):
        d_off[3 * r, r] = 1.0
        d_rho[3 * r + 1, 3 * r + a], d_rho[3 * r + 1, 3 * r + b] = -sigma * c, -s
        d_rho[3 * r + 2, 3 * r + a], d_rho[3 * r + 2, 3 * r + b] = -sigma * s, c
        d_theta[3 * r + 1] = sigma * rho[r, a] * s - rho[r, b] * c
        d_theta[3 * r + 2] = -sigma * rho[r, a] * c - rho[r, b] * s
    return pred.ravel(), d_rho, d_off, d_theta


def solve_phase_free(rate_hz: float, segments: list[PhaseSegment], g_local: float,
                     g_uncertainty: float) -> PhaseFreeFit | Failure:
    """The intrinsic parameters of one rate from segments whose phases are
    (partly) unknown."""
    axes = {s.axis for s in segments}
    if axes != set(AXES):
        missing = [STATE[3 * r + c] for r in range(3) for c in range(3)
                   if all(c not in _plane(ax) for ax in axes)]
        seen = ", ".join(sorted(axes)) or "none"
        if missing:
            return Failure(rate_hz, f"segments about axes {seen} leave {', '.join(missing)} unmeasured")
        # two axes measure every component, but not the unknown starting angles as well
        return Failure(rate_hz, f"segments about axes {seen} only: rotations without a table angle need all "
                                "three axes to solve their unknown starting angles")
    rho = _start(segments)
    fixed = [s for s in segments if s.fixed]
    if fixed:
        # the axes' signs that the segments with a table angle prescribe
        signs = [np.array(v) for v in np.ndindex(2, 2, 2)]
        cost = [sum(np.sum((_in_plane(s.coef) - (rho * (1 - 2 * v))[:, list(_plane(s.axis))]) ** 2) for s in fixed)
                for v in signs]
        rho = rho * (1 - 2 * signs[int(np.argmin(cost))])
    else:
        # no direction reference: the axes' signs follow the DUT's rough alignment (u along x, v along y,
        # w along z), as the blind axis names do
        rho = rho * np.where(np.diag(rho) < 0, -1.0, 1.0)
    turns = [(0.0, 1.0) if s.fixed else _turn(_polar(rho[:, list(_plane(s.axis))].T @ _in_plane(s.coef)))
             for s in segments]
    free = [k for k, s in enumerate(segments) if not s.fixed]
    sigma = np.array([t[1] for t in turns])
    theta = np.array([t[0] for t in turns])
    offset = np.mean([s.coef.reshape(3, 3)[:, 0] for s in segments], axis=0)
    # weights from each coefficient's variance, as combine uses for the labelled segments (Geist
    # Eqs. 10 and 12); the full covariances are propagated below (a sandwich estimate)
    scale = [1.0 / np.sqrt(np.maximum(np.diag(s.cov), 1e-290)) for s in segments]
    n_par = 12 + len(free)
    column = {k: 12 + j for j, k in enumerate(free)}
    weight = np.concatenate(scale)

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        angles = theta.copy()
        angles[free] = x[12:]
        return x[:9].reshape(3, 3), x[9:12], angles

    def system(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whitened residuals (prediction - coefficients) and their Jacobian."""
        rho, offset, angles = unpack(x)
        resid, jac = [], []
        for k, s in enumerate(segments):
            pred, d_rho, d_off, d_theta = _model(rho, offset, s.axis, angles[k], sigma[k])
            block = np.zeros((9, n_par))
            block[:, :9], block[:, 9:12] = d_rho, d_off
            if k in column:
                block[:, column[k]] = d_theta
            resid.append(pred - s.coef)
            jac.append(block)
        return np.concatenate(resid) * weight, np.vstack(jac) * weight[:, None]

    # tolerance 1e-12: the estimate then agrees with the former hand-written Gauss-Newton loop (steps below
    # 1e-12 relative) within 8e-12 relative, 2e-6 of its uncertainty, on 200 noisy simulated DUTs
    fit = nonlinear(lambda x: system(x)[0], lambda x: system(x)[1], np.r_[rho.ravel(), offset, theta[free]], 1e-12)
    rho, offset, theta = unpack(fit.x)
    # the estimate's response to every segment's coefficients, and through it their covariance
    response = fit.gain * weight[None, :]
    blocks = [response[:, 9 * k : 9 * k + 9] for k in range(len(segments))]
    cov = sum(b @ s.cov @ b.T for b, s in zip(blocks, segments))
    parts = [(segment_input(s.segment, s.axis, s.dof), b[:12] @ s.cov @ b[:12].T) for b, s in zip(blocks, segments)]
    result = IntrinsicResult.from_state(rate_hz, np.r_[rho.ravel(), offset], cov[:12, :12], g_local, g_uncertainty, parts)
    theta_u = np.full(len(segments), np.nan)
    theta_u[free] = np.degrees(np.sqrt(np.diag(cov)[12:]))
    theta_deg = np.where([s.fixed for s in segments], np.nan, np.degrees(theta) % 360.0)
    # consistency of the components measured twice, with the full covariances
    chi2 = sum(float(r @ np.linalg.lstsq(s.cov, r, rcond=None)[0])
               for s, r in zip(segments, np.split(fit.residuals / weight, len(segments))))
    return PhaseFreeFit(result, theta_deg, theta_u, sigma < 0, chi2, fit.dof)
