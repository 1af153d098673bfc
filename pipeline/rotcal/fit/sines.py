"""The three-parameter sine fit, batched (Gaitan 2021 Eq. 17): the normal
equations of all three channels in one pass over a segment's samples, a
second pass for the residual statistics (``fit.normal``), sin and cos of
the table angles by angle addition."""

from __future__ import annotations

import math

import numpy as np

from rotcal.fit.normal import NormalSums, ResidualSums, coefficient_covariance

# # Normal equations of all three channels in one pass over the samples, a
# second pass for the residual statistics; both walk blocks of
# BLOCK_SAMPLES contiguous samples, so every operation is a 1-D numpy call
# on data in the core's cache. (``run_dataset`` keeps BLAS on one thread;
# a threaded dot product here would compete with the segment workers.)

BLOCK_SAMPLES = 32768
PROGRESSION_TOLERANCE_DEG = 1e-9  # far below any table encoder's resolution
_TABLE_SIZE = 4096
_TABLE_STEP_DEG = 360.0 / _TABLE_SIZE  # 0.087890625, exact in binary
_TABLE_SIN = np.sin(2 * np.pi * np.arange(_TABLE_SIZE) / _TABLE_SIZE)
_TABLE_COS = np.cos(2 * np.pi * np.arange(_TABLE_SIZE) / _TABLE_SIZE)
_INNER = 64  # inner length of the two-level progression bases


def sincos_deg(theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of angles in degrees, to a few ulp, by angle addition:
    theta = k h + d with h = 360/4096 deg and |d| <= h/2, so

        sin(theta) = sin(k h) cos(d) + cos(k h) sin(d),
        cos(theta) = cos(k h) cos(d) - sin(k h) sin(d),

    with sin(k h), cos(k h) from a 4096-entry table and sin(d), cos(d) from
    their Taylor series to d^7 and d^6 (|d| < 7.7e-4 rad: truncation below
    1e-28). ``theta - k h`` is exact, so large angles (many turns) lose
    nothing to range reduction.
    """
    k = np.rint(theta_deg * (1.0 / _TABLE_STEP_DEG))
    d = np.deg2rad(theta_deg - k * _TABLE_STEP_DEG)
    index = k.astype(np.int64) & (_TABLE_SIZE - 1)
    d2 = d * d
    sin_d = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0)))
    cos_d = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0))
    sin_k, cos_k = _TABLE_SIN[index], _TABLE_COS[index]
    return sin_k * cos_d + cos_k * sin_d, cos_k * cos_d - sin_k * sin_d


def _progression_bases(step_deg: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of i step for i < n, as sin((64 q + r) step) by angle
    addition of n/64 + 64 sines."""
    outer = np.deg2rad(_INNER * step_deg * np.arange(-(-n // _INNER)))[:, None]
    inner = np.deg2rad(step_deg * np.arange(_INNER))
    sin_a, cos_a, sin_b, cos_b = np.sin(outer), np.cos(outer), np.sin(inner), np.cos(inner)
    return (sin_a * cos_b + cos_a * sin_b).ravel()[:n], (cos_a * cos_b - sin_a * sin_b).ravel()[:n]


class _Sines:
    """sin and cos of a segment's angles block by block. Along a constant
    rotation sampled at a constant rate theta_i = theta_0 + i step, and a
    block starting at angle a gets sin(a + i step) = sin a cos(i step) +
    cos a sin(i step) from bases shared by all blocks; a block off the
    progression (by more than PROGRESSION_TOLERANCE_DEG) uses ``sincos_deg``."""

    def __init__(self, theta_deg: np.ndarray):
        n = theta_deg.size
        self.theta0 = float(theta_deg[0])
        self.step = (float(theta_deg[-1]) - self.theta0) / max(n - 1, 1)
        # the bases only where the first interval is the mean one (never for static steps)
        progression = self.step and n > _INNER and abs(theta_deg[1] - theta_deg[0] - self.step) <= PROGRESSION_TOLERANCE_DEG
        self.bases = _progression_bases(self.step, min(n, BLOCK_SAMPLES)) if progression else None
        self.offsets = self.step * np.arange(min(n, BLOCK_SAMPLES))

    def __call__(self, theta_deg: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        m = theta_deg.size
        if self.bases is not None:
            first = self.theta0 + self.step * start
            off = theta_deg - self.offsets[:m]
            off -= first
            if max(off.max(), -off.min()) <= PROGRESSION_TOLERANCE_DEG:
                sin_a, cos_a = math.sin(math.radians(first)), math.cos(math.radians(first))
                sin_b, cos_b = self.bases[0][:m], self.bases[1][:m]
                return sin_a * cos_b + cos_a * sin_b, cos_a * cos_b - sin_a * sin_b
        return sincos_deg(theta_deg)


def sine3_fit(theta_deg: np.ndarray, channels: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """Least squares of each channel on ``C + A sin(theta) + B cos(theta)``
    (Gaitan 2021 Eq. 17), all channels at once, by normal equations.

    Returns coef (channels x (C, A, B)), the channel-major covariance
    Sigma (x) (X^T X)^-1 with Sigma = R^T R / (n - 3), R^T R (channel x
    channel residual products), and each channel's largest residual
    magnitude and lag-1 residual product sum.
    """
    normal, residual, xtx_inv = sine3_sums(theta_deg, channels)
    rtr = residual.products()
    return residual.coef, coefficient_covariance(rtr, xtx_inv, theta_deg.size), rtr, residual.max_abs, residual.lag


def sine3_sums(theta_deg: np.ndarray, channels: tuple[np.ndarray, ...]) -> tuple[NormalSums, ResidualSums, np.ndarray]:
    """``sine3_fit``'s two passes: the normal sums, the residual sums at the
    solved coefficients, and (X^T X)^-1."""
    n = theta_deg.size
    sines = _Sines(theta_deg)
    spans = [(a, min(a + BLOCK_SAMPLES, n)) for a in range(0, n, BLOCK_SAMPLES)]
    normal, bases = NormalSums(len(channels)), []
    for a, b in spans:
        s, c = sines(theta_deg[a:b], a)
        normal.add(s, c, [y[a:b] for y in channels])
        bases.append((s, c))
    coef, xtx_inv = normal.solve()
    residual = ResidualSums(coef)
    for (a, b), (s, c) in zip(spans, bases):
        residual.add(s, c, [y[a:b] for y in channels])
    return normal, residual, xtx_inv
