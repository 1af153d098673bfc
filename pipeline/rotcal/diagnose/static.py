"""Diagnosis of static recordings (hand poses, jig positions, table steps
without angles): the residuals of the static fit (|a| - g_local per pose,
or the vector residual against a known reference; ``static_model``) tested
against the orientation (``cubic_nonlinearity``, ``quadratic_nonlinearity``
of each channel), against time (``offset_drift``) and against temperature
(``thermal``, when a varying ``temperature_c`` is logged).

The same steps as the table diagnosis (``rotcal.diagnose``): forward
selection among the catalogue extensions, each scored by the chi-square it
removes and eligible when significant at the false-alarm rate per test
``[diagnosis] false_alarm`` (the table diagnosis' key: the same meaning) with
a negative BIC change; the one with the best BIC added, the rest scored
again; then backward elimination of any extension the others made
redundant. The poses are few (tens), so each model is the static fit's
linearisation at its solution (one Jacobian; every nested model a linear
least-squares problem) and only the final model is refitted in full
(Levenberg-Marquardt), giving the effect parameters and the refined
intrinsic parameters.

The statistic is chi-square on k degrees of freedom when the poses' scatter
is their noise; when the static fit estimated an excess scatter (hand poses
rarely rest perfectly) it is Fisher's F on (k, dof) with the scatter
estimated from the larger model, so that the false-alarm rate holds either
way. An effect so selected is modelled only when the model with it also
predicts poses left out one at a time better than the baseline by more
than chance (``combine.heldout``); the comparison is the diagnosis's
``heldout`` sentence, which the recommendation quotes. Where nothing is found, ``detection_limits`` gives the size of each
parameter whose expected statistic reaches the threshold (50 % power) with
this recording's poses and noise: "nothing found" with a size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl
from scipy.special import chdtri, fdtrc, fdtri

from rotcal.combine import StaticReduction
from rotcal.combine.heldout import HeldOut, compare, press
from rotcal.config import DiagnosisConfig
from rotcal.diagnose.candidates import report_parameters
from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.scans import counted, p_is
from rotcal.diagnose.static_model import PoseModel, pose_model
from rotcal.diagnose.static_wander import WANDER_LEVEL, is_slow, wander_p_value
from rotcal.fit.lsq import excess_is_significant, nonlinear
from rotcal.model.effects import effect_named, listed
from rotcal.model.effects.base import Candidate
from rotcal.model.results import IntrinsicResult, whole_fit_input
from rotcal.tables import conform, schema


@dataclass(frozen=True, eq=False)
class StaticDiagnosis:
    """The diagnosis of a static recording: the findings and effect-parameter
    tables, the refined intrinsic result, per finding the weighted residuals
    of the model without it and what they are drawn against (a label, each
    pose's value, the channel), the final model's weighted residuals, and
    the detection limit of every parameter tested (50 % power at the
    false-alarm rate)."""

    findings: pl.DataFrame
    parameters: pl.DataFrame
    refined: tuple[IntrinsicResult, ...]
    before: dict[str, np.ndarray]
    against: dict[str, tuple[str, np.ndarray, int]]
    after: np.ndarray
    limits: dict[str, float]
    poses: int
    method: str
    heldout: str = ""  # the held-out comparison of the model with the effects found against the baseline

    def channel(self, residuals: np.ndarray, r: int) -> np.ndarray:
        """Each pose's residual in channel r (the |a| residual when orientation-free)."""
        return residuals if self.method == "orientation-free" else residuals.reshape(-1, 3)[:, r]


@dataclass(frozen=True, eq=False)
class Test:
    """One nested-model test: the extensions it adds and its numbers."""

    candidates: tuple[Candidate, ...]
    chi2: float        # the chi-square removed (scaled by the excess scatter's estimate under F)
    p_value: float
    delta_bic: float


class Linearised:
    """The static fit linearised at its solution: residuals r0 and the
    Jacobian of every parameter; a nested model's residual sum of squares
    is a linear least-squares problem on its columns."""

    def __init__(self, model: PoseModel):
        self.model = model
        self.theta0 = model.full(model.start)
        self.r0 = model.residuals(self.theta0)
        self.jac = model.jacobian(self.theta0, np.arange(self.theta0.size))
        self.n = self.r0.size

    def cols(self, active: tuple[Candidate, ...]) -> np.ndarray:
        return np.concatenate([self.model.free, *[self.model.columns(c) for c in active]]).astype(int)

    def solve(self, active: tuple[Candidate, ...]) -> tuple[np.ndarray, float]:
        """The parameters of the model with ``active`` and its residual sum of squares."""
        cols = self.cols(active)
        step = np.linalg.lstsq(self.jac[:, cols], -self.r0, rcond=None)[0]
        theta = self.theta0.copy()
        theta[cols] += step
        return theta, float(np.sum((self.r0 + self.jac[:, cols] @ step) ** 2))

    def dof(self, active: tuple[Candidate, ...]) -> int:
        return self.n - self.cols(active).size

    def test(self, smaller: tuple[Candidate, ...], larger: tuple[Candidate, ...]) -> Test:
        """The test of ``larger`` against the nested ``smaller``."""
        k = self.cols(larger).size - self.cols(smaller).size
        dof = self.dof(larger)
        added = tuple(c for c in larger if c not in smaller)
        if dof <= 0:   # more parameters than residuals: nothing to test
            return Test(added, 0.0, 1.0, 0.0)
        removed = max(self.solve(smaller)[1] - self.solve(larger)[1], 0.0)
        if self.model.excess:
            scale = self.solve(larger)[1] / dof
            stat = removed / scale
            p = float(fdtrc(k, dof, stat / k))  # scipy.stats.f.sf: stat >= 0
        else:
            stat = removed
            p = chi2_sf(stat, k)
        return Test(added, stat, p, -stat + k * np.log(self.n))

    def limit(self, cand: Candidate, active: tuple[Candidate, ...], alpha: float) -> dict[str, float]:
        """Each of the candidate's parameters at the size whose expected
        statistic equals the test's threshold (about 50 % power), the model
        ``active`` (less the candidate) fitted beside it."""
        others = tuple(c for c in active if c.effect != cand.effect)
        base = self.jac[:, self.cols(others)]
        k = len(cand.names)
        dof = self.dof(others + (cand,))
        if dof <= 0:
            return dict.fromkeys(cand.names, float("inf"))
        if self.model.excess:
            # f.isf(alpha) as scipy.stats computes it (its ppf at 1 - alpha), to the bit
            threshold = k * float(fdtri(k, dof, 1.0 - alpha)) * self.solve(others + (cand,))[1] / dof
        else:
            threshold = float(chdtri(k, alpha))  # scipy.stats.chi2.isf
        out = {}
        for name, col in zip(cand.names, self.model.columns(cand)):
            column = self.jac[:, col]
            free = column - base @ np.linalg.lstsq(base, column, rcond=None)[0]
            # a column the baseline absorbs (k3 on +-1 g poses only: a sensitivity) has no limit
            seen = np.linalg.norm(free) > 1e-6 * np.linalg.norm(column)
            out[name] = float(np.sqrt(threshold) / np.linalg.norm(free)) if seen else float("inf")
        return out


def select(lin: Linearised, alpha: float) -> tuple[Candidate, ...]:
    """Forward selection by BIC among extensions significant at ``alpha``,
    then backward elimination of any the others made redundant."""
    active: tuple[Candidate, ...] = ()
    while True:
        tests = [lin.test(active, active + (c,)) for c in lin.model.candidates
                 if c not in active and lin.dof(active + (c,)) > 0]
        eligible = [t for t in tests if t.p_value < alpha and t.delta_bic < 0]
        if not eligible:
            break
        best = min(eligible, key=lambda t: (t.delta_bic, t.candidates[0].key))
        active = active + best.candidates
    while active:
        worst = max((lin.test(tuple(c for c in active if c is not d), active).p_value, d.key, d) for d in active)
        if worst[0] < alpha:
            break
        active = tuple(c for c in active if c is not worst[2])
    return active


def refit(lin: Linearised, active: tuple[Candidate, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The final model refitted in full from its linearised solution: the
    parameters, the covariance of its free columns (scaled by the residual
    scatter when the static fit estimated an excess) and those columns."""
    model, cols = lin.model, lin.cols(active)
    theta = lin.solve(active)[0]

    def whole(p: np.ndarray) -> np.ndarray:
        full = theta.copy()
        full[cols] = p
        return full

    fit = nonlinear(lambda p: model.residuals(whole(p)), lambda p: model.jacobian(whole(p), cols), theta[cols])
    theta = whole(fit.x)
    jac = model.jacobian(theta, cols)
    cov = np.linalg.inv(jac.T @ jac)
    if model.excess:
        cov = cov * float(np.sum(model.residuals(theta) ** 2)) / (lin.n - cols.size)
    return theta, cov, cols


def _rms(model: PoseModel, theta: np.ndarray) -> float:
    """RMS of the residuals in output units (|a| - g at the mean responsivity when orientation-free)."""
    r = model.residuals(theta)
    if model.reference is not None:
        raw = np.einsum("kij,kj->ki", model.weights, r.reshape(-1, 3))
        return float(np.sqrt(np.mean(raw**2)))
    state, _ = model.state(theta)
    per_g = np.linalg.norm(state[:9].reshape(3, 3), axis=1).mean() / model.g_local
    return float(np.sqrt(np.mean((r * model.weights * per_g) ** 2)))


def limit_text(size: float) -> str:
    return f"{size:.2g}" if np.isfinite(size) else "not identifiable from these poses"


def _against(model: PoseModel, theta: np.ndarray, cand: Candidate) -> tuple[str, np.ndarray, int]:
    """What an effect's residuals follow, per pose: the channel's output in g
    (the nonlinearities), the time (drift) or the temperature (thermal)."""
    r = "uvw".index(cand.scope)
    at_rest = effect_named(cand.effect).at_rest
    if at_rest == "time" and model.elapsed_s is not None:
        return "time since the first sample (s)", model.elapsed_s, r
    if at_rest == "temperature" and model.excursion_k is not None:
        return "temperature - T_ref (K)", model.excursion_k, r
    state, _ = model.state(theta)
    rows = state[:9].reshape(3, 3)
    return f"output of {cand.scope} (g)", (model.means[:, r] - state[9 + r]) / np.linalg.norm(rows[r]), r


def _limits_text(limits: dict[str, float]) -> str:
    return ", ".join(f"{n} {limit_text(v)}" for n, v in limits.items())


def _rows(lin: Linearised, active: tuple[Candidate, ...], theta: np.ndarray, cov: np.ndarray, cols: np.ndarray,
          alpha: float, dataset: str, unit: str) -> tuple[list[dict], list[dict], dict[str, np.ndarray],
                                                          dict[str, tuple[str, np.ndarray, int]], dict[str, float]]:
    """One findings row per catalogue effect, the detected effects'
    parameters, the residuals without each and what they follow, and every
    tested parameter's detection limit."""
    model = lin.model
    rows: list[dict] = []
    params: list[dict] = []
    before: dict[str, np.ndarray] = {}
    against: dict[str, tuple[str, np.ndarray, int]] = {}
    limits: dict[str, float] = {}
    rms_final = _rms(model, theta)
    where_poses = f"all {len(model.means)} poses"
    logged = frozenset() if model.excursion_k is None else frozenset({"temperature_c"})
    for effect in listed():
        if not effect.needs <= logged:
            continue
        granules = tuple(c for c in model.candidates if c.effect == effect.name)
        row = {"dataset": dataset, "effect": effect.name, "rms_before": rms_final, "rms_after": rms_final}
        if not granules:
            rows.append(row | {"detected": False, "where": "not testable here", "delta_bic": 0.0, "p_value": 1.0,
                               "evidence": effect.not_at_rest})
            continue
        found = tuple(c for c in active if c.effect == effect.name)
        if not found:
            singles = sorted((lin.test(active, active + (c,)).p_value, c.key) for c in granules)
            joint = lin.test(active, active + granules)
            limit = {n: v for c in granules for n, v in lin.limit(c, active, alpha).items()}
            limits |= limit
            rows.append(row | {
                "detected": False, "where": "tested: " + "; ".join(f"channel {c.scope}" for c in granules)
                + f" ({where_poses})", "delta_bic": joint.delta_bic, "p_value": singles[0][0],
                "rms_after": _rms(model, lin.solve(active + granules)[0]),
                "evidence": f"not detected: modelling it on every channel lowers chi-square by {joint.chi2:.1f} "
                            f"(BIC change {joint.delta_bic:+.1f}); the strongest single test ({singles[0][1]}) has "
                            f"{p_is(singles[0][0])}, above the false-alarm rate {alpha:g}; detectable at this "
                            f"level (50 % power): {_limits_text(limit)}"})
            continue
        reduced = tuple(c for c in active if c.effect != effect.name)
        test = lin.test(reduced, active)
        before[effect.name] = model.residuals(lin.solve(reduced)[0])
        against[effect.name] = _against(model, theta, found[0])
        reported = []
        for c in found:
            pos = [int(np.flatnonzero(cols == col)[0]) for col in model.columns(c)]
            reported += report_parameters(c, theta[model.columns(c)], cov[np.ix_(pos, pos)], unit)
        params += [{"dataset": dataset, "effect": effect.name, "axis": "", "parameter": q.name, "value": q.value,
                    "std_uncertainty": q.std_uncertainty, "unit": q.unit} for q in reported]
        text = ", ".join(f"{q.name} = {q.value:.4g} ± {q.std_uncertainty:.2g}" for q in reported)
        rows.append(row | {
            "detected": True, "where": "; ".join(f"channel {c.scope}" for c in found) + f" ({where_poses})",
            "rms_before": _rms(model, lin.solve(reduced)[0]), "delta_bic": test.delta_bic, "p_value": test.p_value,
            "evidence": f"the static poses' residuals follow it: modelling it lowers chi-square by {test.chi2:.0f} on "
                        f"{counted(sum(len(c.names) for c in found), 'parameter')} ({p_is(test.p_value)}, BIC change "
                        f"{test.delta_bic:+.0f}); {text}"})
    return rows, params, before, against, limits


def _refined(model: PoseModel, theta: np.ndarray, cov: np.ndarray, dof: int, g_uncertainty: float) -> IntrinsicResult:
    state, lift = model.state(theta)
    base = lift[:, model.free]
    state_cov = base @ cov[: model.free.size, : model.free.size] @ base.T
    return IntrinsicResult.from_state(0.0, state, state_cov, model.g_local, g_uncertainty,
                                      [(whole_fit_input("model fit", float(dof)), state_cov)])


def diagnose_static(static: StaticReduction, t0_ns: int | None, dataset: str, output_unit: str,
                    g_uncertainty: float, config: DiagnosisConfig) -> StaticDiagnosis | None:
    """Diagnose a static recording from its reduction (``t0_ns`` its first
    sample, None without time stamps); None when the reduction has no fit
    or its poses leave no degree of freedom for a test."""
    model = pose_model(static, t0_ns)
    if model is None or not model.candidates:
        return None
    lin = Linearised(model)
    if lin.dof(()) < 2:
        return None
    alpha = config.false_alarm
    active = against_wander(lin, select(lin, alpha))
    heldout = _held_out(lin, active) if active else None
    if heldout is not None and not heldout.better:  # fits these poses, but does not predict the next: not modelled
        active = ()
    theta, cov, cols = refit(lin, active) if active else (lin.theta0, np.zeros((0, 0)), lin.cols(()))
    rows, params, before, against, limits = _rows(lin, active, theta, cov, cols, alpha, dataset, output_unit)
    refined = (_refined(model, theta, cov, lin.dof(active), g_uncertainty),) if active else ()
    findings = conform(pl.DataFrame(rows, schema=schema("diagnosis").polars_schema), "diagnosis")
    parameters = (conform(pl.DataFrame(params, schema=schema("effect_parameters").polars_schema), "effect_parameters")
                  if params else schema("effect_parameters").empty())
    return StaticDiagnosis(findings, parameters, refined, before, against, model.residuals(theta), limits,
                           len(model.means), static.method, "" if heldout is None else heldout.text("baseline", "refined"))


def against_wander(lin: Linearised, active: tuple[Candidate, ...]) -> tuple[Candidate, ...]:
    """``active`` less the slow effects a wander of the offsets explains as
    well (``static_wander``: p at or above ``WANDER_LEVEL``), the weakest first."""
    model = lin.model
    if model.bounds_s is None or not any(is_slow(c) for c in active):
        return active
    # where the model with the effects leaves no scatter beyond the poses' own noise, no wander competes with them
    theta, _ = lin.solve(active)
    cols = lin.cols(active)
    left = lin.r0 + lin.jac[:, cols] @ (theta[cols] - lin.theta0[cols])
    if not excess_is_significant(float(left @ np.linalg.solve(model.noise, left)), lin.dof(active)):
        return active
    while True:
        tests = [(wander_p_value(lin.r0, lin.jac, lin.cols(tuple(a for a in active if a is not c)),
                                 np.array(model.columns(c)), model.offsets, model.noise, model.pose_of_row,
                                 model.bounds_s), c.key, c) for c in active if is_slow(c)]
        weakest = max(tests, default=None)
        if weakest is None or weakest[0] < WANDER_LEVEL:
            return active
        active = tuple(c for c in active if c is not weakest[2])


def _held_out(lin: Linearised, active: tuple[Candidate, ...]) -> HeldOut:
    """The baseline and the model with ``active`` compared on poses left out
    one at a time (``combine.heldout``), both linearised at the static fit."""
    size = lin.n // len(lin.model.means)
    errors = []
    for model in ((), active):
        cols = lin.cols(model)
        residuals = lin.r0 + lin.jac[:, cols] @ (lin.solve(model)[0][cols] - lin.theta0[cols])
        errors.append(press(residuals, lin.jac[:, cols], size))
    return compare(*errors)
