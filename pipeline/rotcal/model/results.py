"""The result records every reduction returns: the intrinsic parameters of
one rate (``IntrinsicResult``, built by its one constructor
``IntrinsicResult.from_state``), a rate that could not be determined
(``Failure``), and what one reduction of a run produced (``Reduction``).

The intrinsic parameters follow from the state (g r_u, g r_v, g r_w, O)
by Geist 2017 Eqs. 14 and 16 (sensitivities |g r| / g, angles between the
responsivity vectors, offsets); their covariance is propagated to first
order (GUM 5.1.2) from the state's covariance and from g_local's standard
uncertainty. The variance each independent input group contributes (GUM
5.1.3) is kept per group, so that the uncertainty budget and the effective
degrees of freedom (Welch-Satterthwaite, GUM G.4.1) can be written.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.model.outputs import output
from rotcal.model.physics import ANGLE_PAIRS

# BudgetInput.source of an input group that is a whole fit's noise, not split
# per segment or position: the reduction has no finer per-input breakdown
WHOLE_FIT = "fit"

# The coverage probability of every expanded uncertainty rotcal prints or
# writes: U = k u with k the t quantile for the effective degrees of freedom
# (GUM G.4.1, G.6.4); k = 1.96 for infinitely many.
EXPANDED_COVERAGE = 0.95


def coverage_factor(dof: np.ndarray) -> np.ndarray:
    """k_p = t_p(nu_eff) for ``EXPANDED_COVERAGE`` (GUM G.3.4, Table G.2)."""
    from scipy.special import stdtrit  # here: the batch's coordinating process, which plans, never needs scipy (0.7 s)

    return stdtrit(np.asarray(dof, float), 0.5 + EXPANDED_COVERAGE / 2)


def intrinsic_jacobian(state: np.ndarray, g_local: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intrinsic parameters of ``state`` and their Jacobians with respect to
    the state and to g_local (Geist 2017 Eqs. 14 and 16 differentiated)."""
    rho = state[:9].reshape(3, 3)
    norm = np.linalg.norm(rho, axis=1)
    unit = rho / norm[:, None]
    value = np.zeros(9)
    jac = np.zeros((9, 12))
    value[:3] = norm / g_local
    for r in range(3):
        jac[r, 3 * r : 3 * r + 3] = unit[r] / g_local
    for k, (i, j) in enumerate(ANGLE_PAIRS):
        c = float(unit[i] @ unit[j])
        value[3 + k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
        scale = -np.degrees(1.0) / np.sqrt(max(1.0 - c * c, 1e-300))
        jac[3 + k, 3 * i : 3 * i + 3] = scale * (unit[j] - c * unit[i]) / norm[i]
        jac[3 + k, 3 * j : 3 * j + 3] = scale * (unit[i] - c * unit[j]) / norm[j]
    value[6:] = state[9:]
    jac[6:, 9:] = np.eye(3)
    jac_g = np.zeros(9)
    jac_g[:3] = -value[:3] / g_local
    return value, jac, jac_g


@dataclass(frozen=True)
class BudgetInput:
    """One input group of an uncertainty budget: the noise of one segment's
    fit (``segment``, ``axis``, with the fit's residual degrees of freedom),
    a whole fit's noise (source ``WHOLE_FIT``: no per-input breakdown) or
    ``g_local`` (a Type B input, infinite degrees of freedom)."""

    label: str
    source: str
    segment: int | None
    axis: str
    dof: float


G_INPUT = BudgetInput("g_local", "g_local", None, "", float("inf"))


def whole_fit_input(label: str, dof: float) -> BudgetInput:
    """The input group of a reduction whose noise is one fit's as a whole."""
    return BudgetInput(label, WHOLE_FIT, None, "", dof)


@dataclass(frozen=True, eq=False)
class IntrinsicResult:
    """The nine intrinsic parameters of one rate with their covariance.

    ``state`` is (g r_u, g r_v, g r_w, O) in output units with covariance
    ``state_cov``; ``budget`` maps each input group (``inputs``, in the
    same order, ``g_local`` last) to its variance contribution to each
    parameter, and ``state_parts`` holds each noise group's contribution
    to ``state_cov`` (for the dof of other functions of the state). Build it with ``from_state``: every field is derived there.
    """

    rate_hz: float
    value: np.ndarray
    cov: np.ndarray
    state: np.ndarray
    state_cov: np.ndarray
    budget: dict[str, np.ndarray]
    g_local: float
    g_uncertainty: float
    inputs: tuple[BudgetInput, ...]
    state_parts: tuple[np.ndarray, ...]

    @classmethod
    def from_state(cls, rate_hz: float, state: np.ndarray, state_cov: np.ndarray, g_local: float, g_uncertainty: float,
                   noise_parts: Sequence[tuple[BudgetInput, np.ndarray]]) -> IntrinsicResult:
        """The intrinsic parameters of a state (Eqs. 14, 16) with first-order
        propagation; ``noise_parts`` are the independent input groups, each
        with its contribution to ``state_cov`` (they add up to it)."""
        if not noise_parts:
            raise ValueError("an intrinsic result needs its noise input groups (at least one)")
        value, jac, jac_g = intrinsic_jacobian(state, g_local)
        budget = {inp.label: np.einsum("ij,jk,ik->i", jac, part, jac) for inp, part in noise_parts}
        budget[G_INPUT.label] = (jac_g * g_uncertainty) ** 2
        cov = jac @ state_cov @ jac.T + np.outer(jac_g, jac_g) * g_uncertainty**2
        inputs = tuple(inp for inp, _ in noise_parts) + (G_INPUT,)
        return cls(rate_hz, value, cov, state, state_cov, budget, g_local, g_uncertainty, inputs,
                   tuple(part for _, part in noise_parts))

    @property
    def std_uncertainty(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))

    @property
    def responsivity(self) -> np.ndarray:
        """Rows r_u, r_v, r_w in the table frame, output unit per m/s^2."""
        return self.state[:9].reshape(3, 3) / self.g_local

    @property
    def g_sensitivity(self) -> np.ndarray:
        """d(parameters)/d(g_local): nonzero for the sensitivities only."""
        return intrinsic_jacobian(self.state, self.g_local)[2]

    @property
    def dof(self) -> np.ndarray:
        """Each parameter's effective degrees of freedom from its budget
        (Welch-Satterthwaite, GUM G.4.1); inf where only inputs of infinite
        degrees of freedom (g_local, a Type B input) contribute."""
        return _welch_satterthwaite(np.diag(self.cov), [self.budget[inp.label] for inp in self.inputs],
                                    [inp.dof for inp in self.inputs])

    def welch_satterthwaite(self, jac: np.ndarray, jac_g: np.ndarray) -> np.ndarray:
        """The effective degrees of freedom of the quantities y = f(state, g)
        with Jacobians ``jac`` (rows: quantities) and ``jac_g`` (GUM G.4.1):
        each noise group's variance J part J^T, g_local's (J_g u_g)^2."""
        parts = [np.einsum("ij,jk,ik->i", jac, part, jac) for part in self.state_parts] + [(jac_g * self.g_uncertainty) ** 2]
        total = np.diag(jac @ self.state_cov @ jac.T + np.outer(jac_g, jac_g) * self.g_uncertainty**2)
        return _welch_satterthwaite(total, parts, [inp.dof for inp in self.inputs])

    @property
    def coverage_factor(self) -> np.ndarray:
        return coverage_factor(self.dof)

    @property
    def expanded_uncertainty(self) -> np.ndarray:
        return self.coverage_factor * self.std_uncertainty

    @property
    def noise_cov(self) -> np.ndarray:
        """The covariance without the g_local part (the fits' noise only)."""
        jac = intrinsic_jacobian(self.state, self.g_local)[1]
        return jac @ self.state_cov @ jac.T


def _welch_satterthwaite(total: np.ndarray, parts: Sequence[np.ndarray], dofs: Sequence[float]) -> np.ndarray:
    """nu_eff = u^4 / sum(u_i^4 / nu_i) (GUM Eq. G.2b), inputs of infinite dof left out of the sum."""
    terms = np.zeros(len(total))
    for part, dof in zip(parts, dofs):
        terms += np.where(np.isfinite(dof), part**2 / dof, 0.0)
    return np.divide(total**2, terms, out=np.full(len(total), np.inf), where=terms > 0)


@dataclass(frozen=True)
class Failure:
    """A rate (0: the static result) that a reduction could not determine, and why."""

    rate_hz: float
    reason: str


@dataclass(frozen=True, eq=False)
class Table:
    """One output table of a run: ``name`` is both its schema and its file
    stem, an entry of ``model.outputs.OUTPUTS`` (``KeyError`` otherwise)."""

    name: str
    data: pl.DataFrame

    def __post_init__(self) -> None:
        if not output(self.name).is_table:
            raise KeyError(f"{self.name!r} is a run output but not a table")


@dataclass(frozen=True, eq=False)
class Reduction:
    """What one reduction of a run produced: the frame its responsivity
    vectors are in (``table``, ``intrinsic``, ``pose``, ``jig``), its
    intrinsic results and failures per rate, the tables it adds to the run's
    output and its warnings."""

    frame: str
    results: tuple[IntrinsicResult, ...]
    failures: tuple[Failure, ...]
    tables: tuple[Table, ...]
    warnings: tuple[str, ...]

    @property
    def rates(self) -> frozenset[float]:
        """Every rate the reduction answers for, determined or not."""
        return frozenset(r.rate_hz for r in self.results) | frozenset(f.rate_hz for f in self.failures)

    def without(self, rates: frozenset[float]) -> Reduction:
        """The reduction without the ``rates`` another reduction answers
        for: their results, failures and table rows (tables with a
        ``rate_hz`` column) left out."""
        if not rates & self.rates:
            return self
        tables = tuple(Table(t.name, t.data.filter(~pl.col("rate_hz").is_in(list(rates))))
                       if "rate_hz" in t.data.columns else t for t in self.tables)
        return Reduction(self.frame, tuple(r for r in self.results if r.rate_hz not in rates),
                         tuple(f for f in self.failures if f.rate_hz not in rates), tables, self.warnings)
