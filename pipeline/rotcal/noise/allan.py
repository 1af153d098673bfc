"""The overlapping Allan variance of a channel's residuals, pooled over the
contiguous pieces of a recording (segments, steps, poses: the logger pauses
between them), at octave averaging times (IEEE Std 1293-2018 Annex A;
NIST SP 1065 eq. 11), with the equivalent degrees of freedom of each
(NIST SP 1065 5.3, ``allantools.edf_simple``)."""

from __future__ import annotations

from dataclasses import dataclass

import allantools
import numpy as np

MIN_EDF = 2.0  # an averaging time estimated with fewer degrees of freedom says nothing


@dataclass(frozen=True, eq=False)
class AllanVariance:
    """Averaging times (s), the pooled overlapping Allan variance at each
    (output unit^2), its second differences counted and its equivalent
    degrees of freedom for white noise; ``alpha`` sets the edf's noise type."""

    tau_s: np.ndarray
    avar: np.ndarray
    n_terms: np.ndarray
    edf: np.ndarray

    @property
    def adev(self) -> np.ndarray:
        return np.sqrt(self.avar)


def _second_difference_sums(piece: np.ndarray, m: int) -> tuple[float, int]:
    """(sum of squared second differences of the phase at lag m, their
    count) of one contiguous piece of frequency data: x = cumsum(y), so
    x_{i+2m} - 2 x_{i+m} + x_i = m (ybar_2 - ybar_1) (NIST SP 1065 eq. 11)."""
    if piece.size < 2 * m:
        return 0.0, 0
    x = np.concatenate([[0.0], np.cumsum(piece)])
    d = x[2 * m:] - 2 * x[m:-m] + x[:-2 * m]
    return float(d @ d), d.size


def octave_factors(longest: int) -> np.ndarray:
    """m = 1, 2, 4, ... while two averages fit in the longest piece."""
    return 2 ** np.arange(int(np.floor(np.log2(max(longest // 2, 1)))) + 1)


def pooled_avar(pieces: list[np.ndarray], fs_hz: float, factors: np.ndarray | None = None,
                alphas: np.ndarray | None = None) -> AllanVariance:
    """The overlapping Allan variance at tau = m / fs of the pieces pooled:
    the sum of every piece's squared second differences over 2 m^2 times
    their count; one piece gives allantools' ``oadev`` squared. The edf are
    summed over the pieces (independent), ``alphas`` the power-law noise
    type per factor (0 white, -1 flicker, -2 random walk; default white);
    averaging times with fewer than MIN_EDF are left out."""
    longest = max((p.size for p in pieces), default=0)
    factors = octave_factors(longest) if factors is None else np.asarray(factors)
    alphas = np.zeros(factors.size, int) if alphas is None else np.asarray(alphas, int)
    tau, avar, count, edf = [], [], [], []
    for m, alpha in zip(factors, alphas):
        sums = [_second_difference_sums(p, int(m)) for p in pieces]
        total, n = sum(s for s, _ in sums), sum(k for _, k in sums)
        dof = sum(float(allantools.edf_simple(p.size, int(m), int(alpha))) for p, (_, k) in zip(pieces, sums) if k > 0)
        if n == 0 or dof < MIN_EDF:
            continue
        tau.append(m / fs_hz)
        avar.append(total / (2.0 * m * m * n))
        count.append(n)
        edf.append(dof)
    return AllanVariance(np.array(tau), np.array(avar), np.array(count, dtype=np.int64), np.array(edf))
