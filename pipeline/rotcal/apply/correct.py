"""The correction of a recording and its uncertainty, vectorized over samples.

A sample R (output units, channels u, v, w) becomes the specific force
a = P (R - O) in m/s^2 in the calibration's frame (Geist 2017 Eq. 18). Its
covariance from the calibration's joint covariance Sigma of (P row-major, O)
is, to first order (GUM 5.1.2), cov(a_i, a_k) = J_i Sigma J_k^T with
da_i/dP_ij = R_j - O_j and da_i/dO_j = -P_ij. Written with
d~ = (R - O, 1), J_i = M_i d~ for a 12 x 4 matrix M_i, so each element is one
quadratic form d~^T (M_i^T Sigma M_k) d~: ten monomials of d~ per sample
and one small matrix product give all six elements.
The sample's own noise is not part of it: the uncertainty is that of the
calibration applied to the sample.
"""

from __future__ import annotations

import numpy as np

from rotcal.model.calibration import RateCalibration

# the six distinct elements of a symmetric 3 x 3 covariance, row-major upper triangle
COVARIANCE_PAIRS = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def correct(raw: np.ndarray, P: np.ndarray, O: np.ndarray) -> np.ndarray:  # noqa: E741 (the papers' O)
    """a = P (R - O) for ``raw`` of shape (3, n): one matrix product and one
    subtraction of P O (the offsets are small against the outputs, so
    nothing is lost to cancellation in float64)."""
    a = np.empty(raw.shape, np.float64)
    np.matmul(P, raw, out=a)
    a -= (P @ O)[:, None]
    return a


# d~ = (d_u, d_v, d_w, 1): the products d~_a d~_b (a <= b) a quadratic form in d~ is a linear combination of
_MONOMIALS = tuple((a, b) for a in range(4) for b in range(a, 4))
_BLOCK = 1 << 16  # samples per block: the block's monomials stay in the cache


def _quadratic_forms(cal: RateCalibration) -> np.ndarray:
    """The coefficients (6 x 10) of the monomials ``_MONOMIALS`` in
    cov(a_i, a_k) = d~^T (M_i^T Sigma M_k) d~, one row per ``COVARIANCE_PAIRS``."""
    P, sigma = cal.P_matrix, cal.correction_cov
    M = np.zeros((3, 12, 4))
    for i in range(3):
        M[i, 3 * i : 3 * i + 3, :3] = np.eye(3)  # da_i/dP_ij = d_j
        M[i, 9:, 3] = -P[i]                      # da_i/dO_j = -P_ij
    coef = np.zeros((len(COVARIANCE_PAIRS), len(_MONOMIALS)))
    for p, (i, k) in enumerate(COVARIANCE_PAIRS):
        G = M[i].T @ sigma @ M[k]
        coef[p] = [G[a, b] if a == b else G[a, b] + G[b, a] for a, b in _MONOMIALS]
    return coef


def correction_covariance(raw: np.ndarray, cal: RateCalibration) -> np.ndarray:
    """Each sample's covariance of (a_x, a_y, a_z) from the calibration's
    covariance, as the six elements of ``COVARIANCE_PAIRS``: shape (6, n),
    (m/s^2)^2. Evaluated a block of samples at a time as one matrix product
    of the coefficients with the block's monomials."""
    coef, n = _quadratic_forms(cal), raw.shape[1]
    cov = np.empty((len(COVARIANCE_PAIRS), n))
    d = np.ones((4, min(n, _BLOCK)))
    mono = np.empty((len(_MONOMIALS), d.shape[1]))
    for start in range(0, n, _BLOCK):
        stop = min(start + _BLOCK, n)
        m = stop - start
        np.subtract(raw[:, start:stop], cal.O_vector[:, None], out=d[:3, :m])
        for row, (a, b) in enumerate(_MONOMIALS):
            np.multiply(d[a, :m], d[b, :m], out=mono[row, :m])
        np.matmul(coef, mono[:, :m], out=cov[:, start:stop])
    # the diagonal is a variance: rounding must not make it negative
    for p, (i, k) in enumerate(COVARIANCE_PAIRS):
        if i == k:
            np.maximum(cov[p], 0.0, out=cov[p])
    return cov


def standard_uncertainty(cov: np.ndarray) -> np.ndarray:
    """u(a_x), u(a_y), u(a_z) (shape (3, n)) from ``correction_covariance``."""
    return np.sqrt(cov[[COVARIANCE_PAIRS.index((i, i)) for i in range(3)]])


def full_covariance(cov: np.ndarray) -> np.ndarray:
    """The nine row-major elements (shape (9, n)) of each sample's 3 x 3
    covariance, as ``sensor_msgs/msg/Imu`` holds it."""
    index = [COVARIANCE_PAIRS.index((min(i, k), max(i, k))) for i in range(3) for k in range(3)]
    return cov[index]
