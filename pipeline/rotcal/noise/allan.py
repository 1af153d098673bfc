"""The overlapping Allan variance of a channel's residuals, pooled over the
contiguous pieces of a recording (segments, steps, poses: the logger pauses
between them), at octave averaging times (IEEE Std 1293-2018 Annex A;
NIST SP 1065 eq. 11), with the equivalent degrees of freedom of each
(NIST SP 1065 5.3, Table 5)."""

from __future__ import annotations

from dataclasses import dataclass

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


def octave_factors(longest: int) -> np.ndarray:
    """m = 1, 2, 4, ... while two averages fit in the longest piece."""
    return 2 ** np.arange(int(np.floor(np.log2(max(longest // 2, 1)))) + 1)


def edf_simple(n: int, m: int, alpha: int) -> float:
    """The equivalent degrees of freedom of the overlapping Allan variance of
    ``n`` samples at averaging factor m, by the simple formulas of NIST SP
    1065 Table 5 (Stein 1985) for white (alpha 0), flicker (-1) and random
    walk (-2) frequency noise; allantools' ``edf_simple`` to rounding
    (``tests/test_noise_identification.py``), written out here because
    importing allantools (and scipy.stats with it) costs a run's process
    half a second. A piece too short for the formula gives 0."""
    n_f, m_f = float(n), float(m)
    if alpha == -2:
        if n <= 3:
            return 0.0
        return (n_f - 2) / (m_f * (n_f - 3) ** 2) * ((n_f - 1) ** 2 - 3 * m_f * (n_f - 1) + 4 * m_f**2)
    if alpha == -1:
        return 2 * (n_f - 2) / (2.3 * n_f - 4.9) if m == 1 else 5 * n_f**2 / (4 * m_f * (n_f + 3 * m_f))
    return (3 * (n_f - 1) / (2 * m_f) - 2 * (n_f - 2) / n_f) * (4 * m_f**2 / (4 * m_f**2 + 5))


def _edf(sizes: list[int], m: int, alpha: int) -> float:
    """The summed equivalent degrees of freedom of the pieces long enough for
    m (each distinct length computed once: a plan's pieces share a few)."""
    lengths, counts = np.unique(np.asarray(sizes, dtype=np.int64), return_counts=True)
    return sum(int(k) * max(edf_simple(int(n), m, alpha), 0.0) for n, k in zip(lengths, counts) if n >= 2 * m)


def pooled_avar(pieces: list[np.ndarray], fs_hz: float, factors: np.ndarray | None = None) -> AllanVariance:
    """The overlapping Allan variance at tau = m / fs of the pieces pooled:
    the sum of every piece's squared second differences of the phase
    x = cumsum(y) at lag m (x_{i+2m} - 2 x_{i+m} + x_i = m (ybar_2 - ybar_1),
    NIST SP 1065 eq. 11) over 2 m^2 times their count; one piece gives
    allantools' ``oadev`` squared. The edf are those of white noise summed
    over the pieces (``with_edf`` for another noise type); averaging times
    with fewer than MIN_EDF are left out."""
    return pooled_avars([p[:, None] for p in pieces], fs_hz, factors)[0]


def pooled_avars(pieces: list[np.ndarray], fs_hz: float, factors: np.ndarray | None = None) -> list[AllanVariance]:
    """``pooled_avar`` of every column of the pieces (n_i, channels) at once."""
    sizes = [p.shape[0] for p in pieces]
    pooled = PooledAllan(octave_factors(max(sizes, default=0)) if factors is None else np.asarray(factors),
                         pieces[0].shape[1] if pieces else 1)
    for piece in pieces:
        pooled.add(piece)
    return pooled.result(fs_hz, None if factors is None else np.asarray(factors))


class PooledAllan:
    """The sums ``pooled_avars`` takes over the pieces, added a piece at a
    time (a capture read block by block gives each segment's pieces as the
    segment is fitted, then lets them go): per averaging factor of
    ``factors`` (at least those of the longest piece to come) each
    channel's sum of squared second differences and their count, and the
    pieces' lengths. The same sums in the same order as the pieces held whole."""

    def __init__(self, factors: np.ndarray, channels: int):
        self.factors = [int(m) for m in factors]
        self.total = [np.zeros(channels) for _ in self.factors]
        self.count = [0 for _ in self.factors]
        self.channels = channels
        self.sizes: list[int] = []

    def add(self, piece: np.ndarray) -> None:
        """One piece (n, channels) of residuals."""
        x = np.empty((piece.shape[0] + 1, piece.shape[1]))  # the phase, 0 then the cumulative sums
        x[0] = 0.0
        np.cumsum(piece, axis=0, out=x[1:])
        self.sizes.append(piece.shape[0])
        for k, m in enumerate(self.factors):
            if x.shape[0] - 1 >= 2 * m:
                # x_{i+2m} - 2 x_{i+m} + x_i, into one array (a long segment is held whole while it is pooled)
                d = np.multiply(x[m:-m], 2.0)
                np.subtract(x[2 * m:], d, out=d)
                np.add(d, x[:-2 * m], out=d)
                self.total[k], self.count[k] = self.total[k] + np.einsum("ij,ij->j", d, d), self.count[k] + d.shape[0]

    def result(self, fs_hz: float, factors: np.ndarray | None = None) -> list[AllanVariance]:
        """Each channel's pooled variance at ``factors`` (default the octaves of the longest piece added)."""
        chosen = octave_factors(max(self.sizes, default=0)) if factors is None else factors
        tau, avar, count, edf = [], [], [], []
        for m in (int(k) for k in chosen):
            k = self.factors.index(m)
            total, n = self.total[k], self.count[k]
            dof = _edf(self.sizes, m, 0)
            if n == 0 or dof < MIN_EDF:
                continue
            tau.append(m / fs_hz)
            avar.append(total / (2.0 * m * m * n))
            count.append(n)
            edf.append(dof)
        values = np.array(avar).reshape(len(tau), self.channels)
        return [AllanVariance(np.array(tau), values[:, c], np.array(count, dtype=np.int64), np.array(edf))
                for c in range(self.channels)]


def with_edf(av: AllanVariance, sizes: list[int], alphas: np.ndarray, fs_hz: float) -> AllanVariance:
    """``av`` with each tau's edf for its power-law noise type ``alphas``
    (0 white, -1 flicker, -2 random walk; NIST SP 1065 Table 5.s simple
    forms) over pieces of ``sizes`` samples; averaging times left with
    fewer than MIN_EDF are dropped."""
    edf = np.array([_edf(sizes, int(round(t * fs_hz)), int(a)) for t, a in zip(av.tau_s, alphas)])
    keep = edf >= MIN_EDF
    return AllanVariance(av.tau_s[keep], av.avar[keep], av.n_terms[keep], edf[keep])
