"""The sums of the three-parameter fit, accumulated a block of samples at a time.

Each channel's model against the table angle is linear in (1, sin theta,
cos theta) (Gaitan 2021 Eq. 17), so its least-squares solution needs only
the sums X^T X, X^T y and n, and these are additive: the sums over a
segment are the sums over any partition of its samples into blocks
(``NormalSums``). The residual statistics the fit reports (the channel x
channel residual products R^T R, each channel's largest residual and its
lag-1 product sum) need the coefficients, so they take a second pass,
again additive block by block, the lag-1 product carried across a block
boundary by the block's last residual (``ResidualSums``).

``sines.sine3_fit`` walks a segment in memory block by block through
these two classes; a streaming run feeds them the blocks of a capture read
chunk by chunk, whatever the chunk boundaries, and gets the same fit to
rounding.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np


class NormalSums:
    """X^T X (its six distinct entries: n, sum s, sum c, s.s, s.c, c.c) and
    X^T y (channel x (sum y, s.y, c.y)) of the design (1, sin theta, cos theta)."""

    def __init__(self, n_channels: int = 3):
        self.xtx = np.zeros(6)
        self.xty = np.zeros((n_channels, 3))

    @property
    def n(self) -> int:
        return int(self.xtx[0])

    def add(self, s: np.ndarray, c: np.ndarray, channels: Sequence[np.ndarray]) -> None:
        """A block: sin and cos of its angles, each channel's samples."""
        self.xtx += (s.size, s.sum(), c.sum(), s @ s, s @ c, c @ c)
        for j, y in enumerate(channels):
            self.xty[j] += (y.sum(), s @ y, c @ y)

    @property
    def gram(self) -> np.ndarray:
        """X^T X (3 x 3)."""
        return self.xtx[[0, 1, 2, 1, 3, 4, 2, 4, 5]].reshape(3, 3)

    def solve(self) -> tuple[np.ndarray, np.ndarray]:
        """The coefficients (channel x (C, A, B)) and (X^T X)^-1."""
        xtx_inv = np.linalg.inv(self.gram)
        return self.xty @ xtx_inv, xtx_inv


class ResidualSums:
    """The residuals' statistics at fixed coefficients: R^T R (upper
    triangle), each channel's largest magnitude and its lag-1 and lag-2
    product sums (the last two residuals carried into the next block)."""

    def __init__(self, coef: np.ndarray):
        k = coef.shape[0]
        self.coef = coef
        self.rtr, self.max_abs, self.lag, self.lag2 = np.zeros((k, k)), np.zeros(k), np.zeros(k), np.zeros(k)
        self.tail = [np.zeros(0)] * k

    def add(self, s: np.ndarray, c: np.ndarray, channels: Sequence[np.ndarray]) -> None:
        """The next block of the segment, in sample order."""
        resid = []
        for j, y in enumerate(channels):
            r = y - self.coef[j, 0]
            r -= self.coef[j, 1] * s
            r -= self.coef[j, 2] * c
            self.max_abs[j] = max(self.max_abs[j], r.max(), -r.min())
            tail = self.tail[j]
            self.lag[j] += r[1:] @ r[:-1] + (tail[-1] * r[0] if tail.size else 0.0)
            # lag 2 across the boundary: the block's first two samples with the two before them
            head, lo = np.concatenate((tail, r[:2])), max(tail.size, 2)
            self.lag2[j] += r[2:] @ r[:-2] + head[lo:] @ head[lo - 2 : head.size - 2]
            self.tail[j] = r[-2:] if r.size >= 2 else head[-2:]
            resid.append(r)
            for i in range(j + 1):
                self.rtr[i, j] += resid[i] @ r

    def products(self) -> np.ndarray:
        """R^T R, the lower triangle from the upper."""
        k = self.rtr.shape[0]
        return np.where(np.arange(k)[:, None] <= np.arange(k), self.rtr, self.rtr.T)


def coefficient_covariance(rtr: np.ndarray, xtx_inv: np.ndarray, n: int) -> np.ndarray:
    """Sigma (x) (X^T X)^-1, channel-major, with Sigma = R^T R / (n - 3)."""
    k = rtr.shape[0]
    return (rtr[:, None, :, None] / max(n - 3, 1) * xtx_inv[None, :, None, :]).reshape(3 * k, 3 * k)


@dataclass(frozen=True, eq=False)
class SineSums:
    """A three-parameter fit as sums over its segment: X^T X, X^T y (channel
    x basis), the coefficients (channel x (C, A, B)) with the residual
    products R^T R at them, and the largest |y| of any channel. A later
    solution on the same samples and angles that is linear in the same basis
    (Geist's simultaneous solution, ``metrology.simultaneous.SegmentSums``)
    needs nothing more, so it need not pass over the samples again."""

    gram: np.ndarray
    xty: np.ndarray
    coef: np.ndarray
    rtr: np.ndarray
    y_max: float
