"""rotcal's least-squares core: nonlinear least squares through scipy's
``least_squares`` (``nonlinear``), and linear least squares with an honest
covariance for fits to a handful of static positions (``ols``: pose means,
table steps, jig positions).

``nonlinear`` minimises sum_i f_i(x)^2 of whitened residuals f (each divided
by its standard deviation) with the Levenberg-Marquardt method (MINPACK);
at the minimum it gives the estimate, the covariance (J^T J)^-1 of the
whitened problem (GUM 6.3; Gauss-Markov) with J the Jacobian of f, the
estimate's first-order response (J^T J)^-1 J^T to the residuals (for a
sandwich covariance when the observations' full covariance is known) and
the residual degrees of freedom.

The estimate is ordinary least squares (AN4399 Eq. 34, the normal
equations), solved through a QR factorisation of the column-scaled design so
that columns of very different size (raw counts next to their cubes) stay
well conditioned.

Its covariance is the sandwich A (Sigma_k + T) A^T with A = (X^T X)^-1 X^T:
Sigma_k is the known noise covariance of observation k (the covariance of a
pose mean), and T the *excess* covariance, the scatter the residuals show
beyond that noise (hand placement, jig tolerance, unmodelled physics). T is
the method-of-moments estimate E[e^T e] = sum_k (1 - h_kk) (Sigma_k + T)
(h the leverages), clipped to be positive semidefinite: the random-effects
("dark uncertainty") model of interlaboratory comparisons, which reduces to
the classical s^2 (X^T X)^-1 when no noise is known. T is modelled only when
the residuals are inconsistent with the noise (their chi-square beyond its
99th percentile, ``excess_is_significant``): estimating it from every chance
fluctuation would overstate the uncertainty of clean data.

With few residual degrees of freedom an estimated T is itself uncertain:
normalised errors then follow Student's t rather than the normal
distribution, and a 95 % interval needs k = t(0.975, dof) > 2.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rotcal.errors import UndeterminedError

CONDITION_LIMIT = 1e10  # of the column-scaled design
EXCESS_LEVEL = 0.99


def excess_is_significant(chi2: float, dof: int, level: float = EXCESS_LEVEL) -> bool:
    """Whether residuals with this chi-square (against the known noise) show
    scatter beyond the noise: chi2 above the ``level`` quantile for ``dof``
    (the chi-square quantile as 2 P^-1(dof / 2, level), P the regularised
    lower incomplete gamma function)."""
    from scipy.special import gammaincinv  # here, not at the top: scipy's import would slow every CLI start

    return dof > 0 and chi2 > 2.0 * gammaincinv(dof / 2.0, level)


@dataclass(frozen=True, eq=False)
class NonlinearFit:
    """The minimum of a whitened least-squares problem: estimate ``x``, the
    whitened residuals and the Jacobian there, and whether the solver
    reported convergence."""

    x: np.ndarray
    residuals: np.ndarray
    jac: np.ndarray
    converged: bool

    @property
    def dof(self) -> int:
        return int(self.residuals.size - self.x.size)

    @property
    def chi2(self) -> float:
        return float(self.residuals @ self.residuals)

    @property
    def cov(self) -> np.ndarray:
        """(J^T J)^-1: the estimate's covariance when the whitened residuals have unit variance."""
        return np.linalg.inv(self.jac.T @ self.jac)

    @property
    def gain(self) -> np.ndarray:
        """(J^T J)^-1 J^T: d(estimate)/d(whitened observation), to first order."""
        return np.linalg.solve(self.jac.T @ self.jac, self.jac.T)


def nonlinear(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
              tolerance: float = 1e-8) -> NonlinearFit:
    """Minimise |fun(x)|^2 from ``x0`` (Levenberg-Marquardt, parameters
    scaled by the Jacobian's columns); ``fun`` returns whitened residuals,
    ``jac`` their Jacobian, ``tolerance`` the relative change of x, of the
    cost and of the gradient at which the iteration stops."""
    from scipy.optimize import least_squares  # here, not at the top: scipy's import would slow every CLI start

    fit = least_squares(fun, x0, jac=jac, method="lm", x_scale="jac", xtol=tolerance, ftol=tolerance, gtol=tolerance)
    return NonlinearFit(fit.x, fit.fun, fit.jac, bool(fit.status > 0))


@dataclass(frozen=True, eq=False)
class LinearFit:
    """Coefficients ``coef`` (p, m) of m right-hand sides sharing one design,
    their covariance (m p, m p), right-hand side major (all p coefficients of
    column 0 first), residuals (n, m), excess covariance T (m, m), the
    residual degrees of freedom per right-hand side and the chi-square of
    the residuals against the known noise (NaN when none is known)."""

    coef: np.ndarray
    cov: np.ndarray
    residuals: np.ndarray
    excess_cov: np.ndarray
    dof: int
    chi2: float

    @property
    def sum_sq_residual(self) -> np.ndarray:
        return np.einsum("km,km->m", self.residuals, self.residuals)


def psd_part(matrix: np.ndarray) -> np.ndarray:
    """The positive semidefinite part of a symmetric matrix (negative
    eigenvalues set to zero)."""
    vals, vecs = np.linalg.eigh((matrix + matrix.T) / 2)
    return (vecs * np.maximum(vals, 0.0)) @ vecs.T


def _chi2(resid: np.ndarray, noise: np.ndarray) -> float:
    """sum_k e_k' Sigma_k^-1 e_k over observations with a non-singular noise covariance."""
    ok = np.linalg.det(noise) > 0
    if not np.any(ok):
        return float("inf")
    return float(np.einsum("ki,kij,kj->", resid[ok], np.linalg.inv(noise[ok]), resid[ok]))


@dataclass(frozen=True, eq=False)
class Solution:
    """What least squares on one design ``x`` (n, p) shares across right-hand
    sides: Q of the column-scaled design's QR and ``a`` = (X^T X)^-1 X^T (p, n)."""

    q: np.ndarray
    a: np.ndarray

    def coef(self, y: np.ndarray) -> np.ndarray:
        """The coefficients (p, m) of every column of ``y`` (n, m), as ``ols`` gives them."""
        return self.a @ y.reshape(y.shape[0], -1)


def least_squares_solution(x: np.ndarray) -> Solution:
    """The QR solution of the design ``x`` (n, p), on unit-RMS columns.
    Raises ``UndeterminedError`` when the design does not determine the coefficients."""
    n, p = x.shape
    if n < p:
        raise UndeterminedError(f"{n} positions cannot determine {p} coefficients")
    scale = np.sqrt(np.mean(x * x, axis=0))
    scale[scale == 0] = 1.0
    q, r = np.linalg.qr(x / scale)
    sv = np.linalg.svd(r, compute_uv=False)
    if sv[-1] <= sv[0] / CONDITION_LIMIT:
        raise UndeterminedError(
            f"the {n} positions do not determine the {p} coefficients (design condition number "
            f"{sv[0] / max(sv[-1], 1e-300):.2g}): they are too few or too alike")
    return Solution(q, np.linalg.solve(r, q.T) / scale[:, None])


def ols(x: np.ndarray, y: np.ndarray, noise_cov: np.ndarray | None = None, solution: Solution | None = None) -> LinearFit:
    """Least squares of every column of ``y`` (n, m) on the design ``x`` (n, p).

    ``noise_cov`` (n, m, m) is the covariance of each observation's m values;
    None means unknown, and then an exact fit (no residual degrees of
    freedom) has undetermined (NaN) covariance. ``solution``: the design's
    ``least_squares_solution`` when the caller has it. Raises
    ``UndeterminedError`` when the design does not determine the coefficients.
    """
    y2 = y.reshape(y.shape[0], -1)
    n, p = x.shape
    m = y2.shape[1]
    solved = least_squares_solution(x) if solution is None else solution
    q, a = solved.q, solved.a  # a (p, n) = (X^T X)^-1 X^T
    coef = a @ y2
    resid = y2 - x @ coef
    dof = n - p
    noise = np.zeros((n, m, m)) if noise_cov is None else noise_cov.reshape(n, m, m)
    chi2 = float("nan") if noise_cov is None else _chi2(resid, noise)
    if noise_cov is None and dof > 0:
        excess = resid.T @ resid / dof
    elif dof > 0 and excess_is_significant(chi2, m * dof):
        leverage = np.einsum("ij,ij->i", q, q)
        excess = psd_part((resid.T @ resid - np.einsum("k,kij->ij", 1.0 - leverage, noise)) / dof)
    elif dof > 0:
        excess = np.zeros((m, m))
    else:
        excess = np.full((m, m), np.nan) if noise_cov is None else np.zeros((m, m))
    total = noise + excess[None]
    cov = np.einsum("ik,krs,jk->risj", a, total, a).reshape(m * p, m * p)
    return LinearFit(coef, cov, resid, excess, dof, chi2)
