"""Combine: per rate, the segment fits into the responsivity vectors and the
nine intrinsic parameters, with first-order (GUM) propagation of the full
covariance of every fit coefficient and of g_local.

Rotation about axis s gives (docs/conventions.md, Geist 2017 Eqs. 5 to 9)

    A = -g r_a,   B = g r_b,   C = O_rs,

with (a, b) = (y, z), (x, z), (x, y) for s = x, y, z. Every component of a
vector is measured by two axes (Geist's r_s1, r_s2) and every offset by
three. rotcal combines the estimates of each by their inverse-variance
weighted mean: Geist's Eqs. 10 and 12 when the standard errors are equal,
and the best linear unbiased estimate when they are not. Uncertainties are
propagated through the linear combination and the Jacobians of Eqs. 14 and
16 with every covariance kept, instead of the printed Eqs. 11, 13, 15 and
17 (docs/method.md, "Printing errors in the papers": Eqs. 11 and 13 overstate a mean's standard error by sqrt(2)
and sqrt(3); Eq. 17 pairs the wrong terms and drops correlations).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.model.physics import AXES, CHANNELS, COS_COMPONENT, INTRINSIC, SIN_COMPONENT, axis_index
from rotcal.model.results import BudgetInput, Failure, IntrinsicResult, Reduction, Table
from rotcal.tables import conform, schema

STATE = tuple(f"rho_{r}{s}" for r in CHANNELS for s in AXES) + tuple(f"O_{r}" for r in CHANNELS)


@dataclass(frozen=True, eq=False)
class Estimate:
    """One measurement of a state element: coefficient ``index`` of segment
    ``segment``'s 9-vector, times ``sign``."""

    target: int
    segment: int
    axis: str
    index: int
    sign: float


@dataclass(frozen=True, eq=False)
class SegmentCoefficients:
    """A segment's fitted 9-vector (channel-major C, A, B) and covariance."""

    segment: int
    axis: str
    coef: np.ndarray
    cov: np.ndarray
    dof: int = 0


def segment_coefficients(fits: pl.DataFrame) -> list[SegmentCoefficients]:
    """Rebuild each ok segment's 9-vector and 9 x 9 covariance from the fits
    table (rows ordered by segment and channel with numpy: a polars sort of
    so small a table costs more than the rebuild)."""
    ok = fits.filter(pl.col("status") == "ok")
    n = ok.height // 3
    rank = {c: i for i, c in enumerate(CHANNELS)}
    segment = ok["segment"].to_numpy()
    order = np.lexsort((np.array([rank[c] for c in ok["channel"].to_list()], np.int64), segment))
    coef = ok.select("C", "A", "B").to_numpy()[order].reshape(n, 9)
    # blocks[s, r, k] is the 3 x 3 covariance of channel r's (C, A, B) with channel k's
    blocks = np.stack([ok[f"cov_{c}"].list.to_array(9).to_numpy()[order] for c in CHANNELS], axis=1).reshape(n, 3, 3, 3, 3)
    cov = blocks.transpose(0, 1, 3, 2, 4).reshape(n, 9, 9)
    first = order[::3]
    axis, dof = ok["axis"].to_numpy()[first], ok["dof"].to_numpy()[first]
    return [SegmentCoefficients(int(segment[j]), str(axis[i]), coef[i], cov[i], int(dof[i])) for i, j in enumerate(first)]


RateSegments = list[tuple[float, list["SegmentCoefficients"]]]  # rate_segments' answer: (rate, its segments)


def rate_segments(fits: pl.DataFrame) -> RateSegments:
    """The ok static and rotation segments of every rate, rates ordered by
    magnitude (rate 0, the static result, first). The stages that read one
    fits table several times are handed its answer (``by_rate``) by the run."""
    fitted = fits.filter(pl.col("kind").is_in(["static", "rotation"]))
    rates = sorted(set(fitted["rate_hz"].to_list()), key=lambda r: (abs(r), r))
    rate_of = dict(fitted.select("segment", "rate_hz").iter_rows())
    segments = segment_coefficients(fitted)  # once for all rates: a polars pass per rate cost 15 ms a dataset
    return [(rate, [s for s in segments if rate_of[s.segment] == rate]) for rate in rates]


def estimates_for(segments: list[SegmentCoefficients]) -> list[Estimate]:
    """Every (state element, coefficient) pair the segments provide."""
    out = []
    for k, seg in enumerate(segments):
        a = axis_index(seg.axis)
        for r in range(3):
            out.append(Estimate(3 * r + SIN_COMPONENT[a], k, seg.axis, 9 * k + 3 * r + 1, -1.0))
            out.append(Estimate(3 * r + COS_COMPONENT[a], k, seg.axis, 9 * k + 3 * r + 2, 1.0))
            out.append(Estimate(9 + r, k, seg.axis, 9 * k + 3 * r, 1.0))
    return out


def combination_matrix(estimates: list[Estimate], variances: np.ndarray, n_obs: int) -> np.ndarray:
    """L (12 x n_obs): inverse-variance weighted means (Geist Eqs. 10 and 12).

    Noise-free estimates (zero variance) get equal, dominant weights.
    """
    L = np.zeros((len(STATE), n_obs))
    weight = 1.0 / np.maximum(variances, 1e-290)
    for e in estimates:
        L[e.target, e.index] = e.sign * weight[e.index]
    totals = np.abs(L).sum(axis=1, keepdims=True)
    return np.divide(L, totals, out=np.zeros_like(L), where=totals > 0)


@dataclass(frozen=True, eq=False)
class LinearStage:
    """The linear part of a rate's combination: every segment's coefficient
    vector stacked (``coef``), their block-diagonal covariance (``cov``;
    segments are independent) and the combination matrix ``L``, so that
    state = L coef."""

    rate_hz: float
    segments: tuple[SegmentCoefficients, ...]
    coef: np.ndarray
    cov: np.ndarray
    L: np.ndarray

    @property
    def state(self) -> np.ndarray:
        return self.L @ self.coef

    @property
    def state_cov(self) -> np.ndarray:
        return self.L @ self.cov @ self.L.T


def linear_stage(rate_hz: float, segments: list[SegmentCoefficients]) -> LinearStage | Failure:
    """Stack a rate's segments and build L; a failure when some state element
    is measured by no segment."""
    estimates = estimates_for(segments)
    counts = np.bincount([e.target for e in estimates], minlength=len(STATE))
    if np.any(counts == 0):
        missing = [STATE[i] for i in np.flatnonzero(counts == 0)]
        axes = sorted({s.axis for s in segments}) or ["none"]
        return Failure(rate_hz, f"segments about axes {', '.join(axes)} leave {', '.join(missing)} unmeasured")
    coef = np.concatenate([s.coef for s in segments])
    cov = np.zeros((coef.size, coef.size))
    for k, seg in enumerate(segments):
        cov[9 * k : 9 * k + 9, 9 * k : 9 * k + 9] = seg.cov
    return LinearStage(rate_hz, tuple(segments), coef, cov, combination_matrix(estimates, np.diag(cov), coef.size))


def segment_input(segment: int, axis: str, dof: int) -> BudgetInput:
    """The budget input group of one segment's noise (dof 0: treated as known)."""
    return BudgetInput(f"segment {segment} ({axis})", "noise", segment, axis, float(dof or np.inf))


def combine_rate(rate_hz: float, segments: list[SegmentCoefficients], g_local: float,
                 g_uncertainty: float) -> IntrinsicResult | Failure:
    """The intrinsic parameters of one rate from its segments."""
    stage = linear_stage(rate_hz, segments)
    if isinstance(stage, Failure):
        return stage
    parts = []
    for k, seg in enumerate(segments):
        Lk = stage.L[:, 9 * k : 9 * k + 9]
        parts.append((segment_input(seg.segment, seg.axis, seg.dof), Lk @ seg.cov @ Lk.T))
    return IntrinsicResult.from_state(rate_hz, stage.state, stage.state_cov, g_local, g_uncertainty, parts)


def combine(fits: pl.DataFrame, g_local: float, g_uncertainty: float,
            by_rate: RateSegments | None = None) -> list[IntrinsicResult | Failure]:
    """Every rate's intrinsic parameters (rate 0 is the static result);
    ``by_rate``: ``rate_segments(fits)`` when the caller has it."""
    return [combine_rate(rate, segs, g_local, g_uncertainty) for rate, segs in by_rate or rate_segments(fits)]


def reduce_labelled(fits: pl.DataFrame, g_local: float, g_uncertainty: float, dataset: str,
                    by_rate: RateSegments | None = None) -> Reduction:
    """The reduction of the segments whose phase is the table angle: every
    rate's result in the table frame, with the ``components`` table."""
    by_rate = rate_segments(fits) if by_rate is None else by_rate
    combined = combine(fits, g_local, g_uncertainty, by_rate)
    results = tuple(r for r in combined if isinstance(r, IntrinsicResult))
    return Reduction("table", results, tuple(f for f in combined if isinstance(f, Failure)),
                     (Table("components", components_frame(fits, list(results), dataset, by_rate)),), ())


def units(output_unit: str) -> tuple[str, ...]:
    return (f"{output_unit}/(m/s^2)",) * 3 + ("deg",) * 3 + (output_unit,) * 3


def intrinsic_frame(results: list[IntrinsicResult], dataset: str, model: str, output_unit: str) -> pl.DataFrame:
    """The long ``intrinsic`` table (docs/outputs.md)."""
    rows = [
        {"dataset": dataset, "model": model, "rate_hz": res.rate_hz, "parameter": name, "value": val,
         "std_uncertainty": u, "dof": dof if np.isfinite(dof) else None, "coverage_factor": k, "expanded_uncertainty": k * u,
         "unit": unit}
        for res in results
        for name, val, u, dof, k, unit in zip(INTRINSIC, res.value, res.std_uncertainty, res.dof, res.coverage_factor,
                                              units(output_unit))
    ]
    return conform(pl.DataFrame(rows, schema=schema("intrinsic").polars_schema), "intrinsic") if rows else schema("intrinsic").empty()


def components_frame(fits: pl.DataFrame, results: list[IntrinsicResult], dataset: str,
                     rates: RateSegments | None = None) -> pl.DataFrame:
    """Each responsivity component's per-segment estimates and combination."""
    rows = []
    by_rate = dict(rate_segments(fits) if rates is None else rates)
    for res in results:
        segs = by_rate[res.rate_hz]
        coef = np.concatenate([s.coef for s in segs])
        var = np.concatenate([np.diag(s.cov) for s in segs])
        for e in estimates_for(segs):
            if e.target >= 9:
                continue
            rows.append({"dataset": dataset, "rate_hz": res.rate_hz, "channel": CHANNELS[e.target // 3],
                         "component": AXES[e.target % 3], "source_axis": e.axis, "segment": segs[e.segment].segment,
                         "value": e.sign * coef[e.index] / res.g_local, "std_uncertainty": np.sqrt(var[e.index]) / res.g_local})
        for t in range(9):
            rows.append({"dataset": dataset, "rate_hz": res.rate_hz, "channel": CHANNELS[t // 3],
                         "component": AXES[t % 3], "source_axis": "combined", "segment": None,
                         "value": res.state[t] / res.g_local, "std_uncertainty": np.sqrt(res.state_cov[t, t]) / res.g_local})
    return conform(pl.DataFrame(rows, schema=schema("components").polars_schema), "components") if rows else schema("components").empty()
