"""The correction of a recording and its uncertainty, vectorized over samples.

A sample R (output units, channels u, v, w) becomes the specific force
a = P (R - O) in m/s^2 in the calibration's frame (Geist 2017 Eq. 18). Its
covariance from the calibration's joint covariance Sigma of (P row-major, O)
is, to first order (GUM 5.1.2), cov(a_i, a_k) = J_i Sigma J_k^T with
da_i/dP_ij = R_j - O_j and da_i/dO_j = -P_ij. Written with
d~ = (R - O, 1), J_i = M_i d~ for a 12 x 4 matrix M_i, so each element is one
quadratic form d~^T (M_i^T Sigma M_k) d~ evaluated for every sample at once.
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


def _sensitivity_forms(cal: RateCalibration) -> np.ndarray:
    """G_ik = M_i^T Sigma M_k (4 x 4) for the pairs of ``COVARIANCE_PAIRS``,
    stacked side by side as a 4 x 24 matrix."""
    P, sigma = cal.P_matrix, cal.correction_cov
    M = np.zeros((3, 12, 4))
    for i in range(3):
        M[i, 3 * i : 3 * i + 3, :3] = np.eye(3)  # da_i/dP_ij = d_j
        M[i, 9:, 3] = -P[i]                      # da_i/dO_j = -P_ij
    return np.hstack([M[i].T @ sigma @ M[k] for i, k in COVARIANCE_PAIRS])


def correction_covariance(raw: np.ndarray, cal: RateCalibration) -> np.ndarray:
    """Each sample's covariance of (a_x, a_y, a_z) from the calibration's
    covariance, as the six elements of ``COVARIANCE_PAIRS``: shape (6, n), (m/s^2)^2."""
    n = raw.shape[1]
    d = np.empty((n, 4))
    d[:, :3] = (raw - cal.O_vector[:, None]).T
    d[:, 3] = 1.0
    forms = (d @ _sensitivity_forms(cal)).reshape(n, len(COVARIANCE_PAIRS), 4)
    cov = np.einsum("npa,na->pn", forms, d)
    # the diagonal is a sum of squares: rounding must not make it negative
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
