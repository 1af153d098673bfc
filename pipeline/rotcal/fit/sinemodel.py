"""The sine model's generalised least-squares system, shared by the
four-parameter fit (``sinefit4``) and the simultaneous solution
(``simultaneous``).

Every prediction and Jacobian column of both fits is a combination of the
five basis functions z = (1, sin theta, cos theta, psi sin theta,
psi cos theta), psi the commanded angle travelled since the segment's first
sample (radians): a channel's prediction is z . m_r and the Jacobian of
channel r is z D_r, D_r a 5 x P matrix. So the normal equations of a
segment, with the channels' noise precision W (3 x 3), are

    N = sum_ab W_ab D_a^T (Z^T Z) D_b,    rhs = sum_ab W_ab D_a^T Z^T e_b,

small matrices built from O(n) sums: no tall matrix products, which keeps
the cost linear in the samples and out of multithreaded BLAS.
"""

from __future__ import annotations

import numpy as np

NOISE_FREE = 1e-9  # residuals below this fraction of the signal are rounding: the data are noise-free


def basis(theta_rad: np.ndarray, psi_rad: np.ndarray) -> np.ndarray:
    """z (n, 5) = 1, sin, cos, psi sin, psi cos."""
    sin, cos = np.sin(theta_rad), np.cos(theta_rad)
    return np.column_stack([np.ones_like(sin), sin, cos, psi_rad * sin, psi_rad * cos])


def residuals(z: np.ndarray, y: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """y - z m_r per channel; ``coef`` (3, 5) holds the m_r."""
    return y - np.einsum("ni,ri->nr", z, coef)


def precision(resid: np.ndarray, y: np.ndarray, n_params: int) -> np.ndarray | None:
    """Inverse of the channels' residual covariance (``n_params`` fitted per
    channel); None when the residuals are at rounding level (noise-free data)."""
    return precision_from(np.einsum("na,nb->ab", resid, resid), resid.shape[0], float(np.max(np.abs(y))), n_params)


def precision_from(rtr: np.ndarray, n: int, y_max: float, n_params: int) -> np.ndarray | None:
    """``precision`` from the residual products R^T R of ``n`` samples whose
    largest output magnitude is ``y_max`` (sums a streamed run accumulates)."""
    sigma = rtr / max(n - n_params, 1)
    if np.linalg.eigvalsh(sigma)[0] <= (NOISE_FREE * y_max) ** 2:
        return None
    return np.linalg.inv(sigma)


def normal_equations(z: np.ndarray, resid: np.ndarray, design: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, rhs) of one segment: ``design`` (3, 5, P) holds the D_r, ``weight`` W."""
    return normal_from(np.einsum("ni,nj->ij", z, z), np.einsum("ni,nb->ib", z, resid), design, weight)


def normal_from(gram: np.ndarray, ze: np.ndarray, design: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, rhs) from the sums Z^T Z and Z^T e over a segment's samples; the
    basis may be the first m of the five functions (``design`` then (3, m, P)).
    With D the D_r stacked ((3 m) x P), N = D^T (W (x) Z^T Z) D and
    rhs = D^T vec(W (Z^T e)^T): two small matrix products, no contraction
    search (``einsum``'s took longer than the sums). W (x) Z^T Z is formed
    by broadcasting (``np.kron``'s same products, at a seventh of its cost)."""
    stacked = design.reshape(-1, design.shape[2])
    m = gram.shape[0]
    kron = (weight[:, None, :, None] * gram[None, :, None, :]).reshape(weight.shape[0] * m, -1)
    return stacked.T @ kron @ stacked, stacked.T @ (weight @ ze.T).ravel()


def solve(normal: np.ndarray, rhs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(step, N^-1), inverted on unit-diagonal scaling: the rate column is
    ~1e7 times the offset column."""
    scale = np.sqrt(np.diag(normal))
    scaled_inverse = np.linalg.inv(normal / np.outer(scale, scale))
    return scaled_inverse @ (rhs / scale) / scale, scaled_inverse / np.outer(scale, scale)
