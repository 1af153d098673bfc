"""Uncertainty: the budget of every intrinsic parameter (the variance each
input group contributes, GUM 5.1.3) and the optional Monte Carlo propagation
of GUM Supplement 1 (JCGM 101:2008) that checks the first-order result.

Input groups are independent: the noise of each segment's fit (segments are
disjoint runs of samples) and ``g_local`` (a Type B input). Their variance
contributions therefore add up to the combined variance, and the effective
degrees of freedom follow from Welch-Satterthwaite (GUM G.4.1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.labelled import LinearStage, linear_stage, rate_segments, units
from rotcal.config import UncertaintyConfig
from rotcal.model.physics import INTRINSIC, intrinsic_from_vectors
from rotcal.model.results import Failure, IntrinsicResult
from rotcal.tables import conform, schema

COVERAGE_PROBABILITY = math.erf(2.0 / math.sqrt(2.0))  # k = 2 for a normal distribution: 95.45 %
BATCH_DRAWS = 10_000  # GUM S1 7.9.4 b): max(100 / (1 - p), 10^4)


def budget_frame(results: list[IntrinsicResult], dataset: str, output_unit: str) -> pl.DataFrame:
    """The ``uncertainty_budget`` table: per rate and parameter, one row per
    input group and a ``combined`` row with the effective degrees of freedom."""
    rows = []
    for res in results:
        total = np.diag(res.cov)
        for inp in res.inputs:
            rows += _budget_rows(dataset, res.rate_hz, inp.source, inp.segment, inp.axis, res.budget[inp.label], total,
                                 inp.dof, output_unit)
        rows += _budget_rows(dataset, res.rate_hz, "combined", None, "", total, total, res.dof, output_unit)
    if not rows:
        return schema("uncertainty_budget").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("uncertainty_budget").polars_schema, strict=False),
                   "uncertainty_budget")


def _budget_rows(dataset: str, rate_hz: float, source: str, segment: int | None, axis: str, var: np.ndarray,
                 total: np.ndarray, dof, output_unit: str) -> list[dict]:
    dof = np.broadcast_to(np.asarray(dof, float), (9,))
    fraction = np.divide(var, total, out=np.zeros(9), where=total > 0)
    return [
        {"dataset": dataset, "rate_hz": rate_hz, "parameter": name, "source": source, "segment": segment, "axis": axis,
         "variance": var[i], "contribution": np.sqrt(var[i]), "fraction": fraction[i], "dof": dof[i], "unit": unit}
        for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit)))
    ]


@dataclass(frozen=True, eq=False)
class MonteCarloResult:
    """GUM S1 summary of one rate: per parameter the mean, standard
    uncertainty and probabilistically symmetric 95.45 % coverage interval of
    the Monte Carlo sample, the standard deviation of the interval ends that
    the finite sample leaves (from the spread of the batches), the number of
    draws and whether the adaptive procedure (S1 7.9) stabilised before
    ``max_draws``."""

    rate_hz: float
    mean: np.ndarray
    std_uncertainty: np.ndarray
    low: np.ndarray
    high: np.ndarray
    endpoint_numerical_u: np.ndarray
    n_draws: int
    stabilised: bool


def numerical_tolerance(u: np.ndarray) -> np.ndarray:
    """GUM S1 7.9.2: u written with two significant digits, c x 10^l; delta = 10^l / 2."""
    safe = np.where(u > 0, u, 1.0)
    return np.where(u > 0, 0.5 * 10.0 ** (np.floor(np.log10(safe)) - 1), 0.0)


def _draw_batch(stage: LinearStage, g_local: float, g_uncertainty: float, rng: np.random.Generator, n: int) -> np.ndarray:
    """n draws of the nine parameters: each segment's coefficient vector from a
    multivariate t with the fit's residual degrees of freedom and scale
    matrix its covariance (GUM S1 6.4.9, JCGM 102 6.5.3; Gaussian when the
    noise is treated as known), g_local from N(g, u_g^2), pushed through
    state = L coef and Geist 2017 Eqs. 14 and 16."""
    draws = np.empty((n, stage.coef.size))
    for k, seg in enumerate(stage.segments):
        eigval, eigvec = np.linalg.eigh(seg.cov)
        root = eigvec * np.sqrt(np.clip(eigval, 0.0, None))
        z = rng.standard_normal((n, 9)) @ root.T
        if seg.dof > 0:
            z *= np.sqrt(seg.dof / rng.chisquare(seg.dof, n))[:, None]
        draws[:, 9 * k : 9 * k + 9] = seg.coef + z
    g = g_local + g_uncertainty * rng.standard_normal(n)
    state = draws @ stage.L.T
    return intrinsic_from_vectors(state[:, :9].reshape(n, 3, 3) / g[:, None, None], state[:, 9:])


def _summary(sample: np.ndarray) -> np.ndarray:
    """Rows: mean, standard deviation, low and high end of the probabilistically
    symmetric coverage interval."""
    tail = (1.0 - COVERAGE_PROBABILITY) / 2
    low, high = np.quantile(sample, [tail, 1.0 - tail], axis=0)
    return np.vstack([sample.mean(axis=0), sample.std(axis=0, ddof=1), low, high])


def monte_carlo_rate(stage: LinearStage, g_local: float, g_uncertainty: float, rng: np.random.Generator,
                     max_draws: int) -> MonteCarloResult:
    """The adaptive Monte Carlo procedure of GUM S1 7.9.4: batches of 10^4
    draws until twice the standard deviation of the batch results of the
    mean, the standard uncertainty and both interval ends is within the
    numerical tolerance of the standard uncertainty, for every parameter."""
    batches, summaries = [], []
    while True:
        batches.append(_draw_batch(stage, g_local, g_uncertainty, rng, BATCH_DRAWS))
        summaries.append(_summary(batches[-1]))
        if len(batches) < 2:
            continue
        spread = np.std(summaries, axis=0, ddof=1) / np.sqrt(len(summaries))
        means, stds = np.array(summaries)[:, 0], np.array(summaries)[:, 1]
        n = len(batches) * BATCH_DRAWS  # pooled standard deviation of all draws so far, from the batches
        pooled = np.sqrt(((BATCH_DRAWS - 1) * np.sum(stds**2, axis=0) + BATCH_DRAWS * np.sum((means - means.mean(axis=0)) ** 2, axis=0)) / (n - 1))
        stable = bool(np.all(2 * spread <= numerical_tolerance(pooled)[None, :]))
        if stable or n >= max_draws:
            break
    mean, std, low, high = _summary(np.concatenate(batches))
    return MonteCarloResult(stage.rate_hz, mean, std, low, high, spread[2:].max(axis=0), len(batches) * BATCH_DRAWS, stable)


def monte_carlo(fits: pl.DataFrame, g_local: float, g_uncertainty: float, config: UncertaintyConfig) -> list[MonteCarloResult]:
    """Every determined rate's Monte Carlo propagation, seeded per rate from
    ``config.monte_carlo_seed`` (the same inputs give the same draws)."""
    stages = [s for s in (linear_stage(rate, segs) for rate, segs in rate_segments(fits)) if not isinstance(s, Failure)]
    seeds = np.random.SeedSequence(config.monte_carlo_seed).spawn(len(stages))
    return [monte_carlo_rate(stage, g_local, g_uncertainty, np.random.default_rng(seed), config.monte_carlo_max_draws)
            for stage, seed in zip(stages, seeds)]


def monte_carlo_frame(mc: list[MonteCarloResult], results: list[IntrinsicResult], dataset: str, output_unit: str) -> pl.DataFrame:
    """The ``monte_carlo`` table: the Monte Carlo result beside the first-order
    one, and the validation of GUM S1 8.2: the first-order interval
    y +- 2u is validated when both of its ends lie within the numerical
    tolerance of the Monte Carlo interval's ends."""
    first = {res.rate_hz: res for res in results}
    rows = []
    for m in mc:
        res = first[m.rate_hz]
        u = res.std_uncertainty
        d_low = np.abs(res.value - 2 * u - m.low)
        d_high = np.abs(res.value + 2 * u - m.high)
        delta = numerical_tolerance(u)
        for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit))):
            rows.append({
                "dataset": dataset, "rate_hz": m.rate_hz, "parameter": name, "unit": unit,
                "value": res.value[i], "std_uncertainty": u[i],
                "mc_mean": m.mean[i], "mc_std_uncertainty": m.std_uncertainty[i],
                "mc_low": m.low[i], "mc_high": m.high[i], "d_low": d_low[i], "d_high": d_high[i],
                "tolerance": delta[i], "validated": bool(d_low[i] <= delta[i] and d_high[i] <= delta[i]),
                "endpoint_numerical_u": m.endpoint_numerical_u[i],
                "n_draws": m.n_draws, "stabilised": m.stabilised,
            })
    if not rows:
        return schema("monte_carlo").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("monte_carlo").polars_schema, strict=False), "monte_carlo")



def monte_carlo_note(frame: pl.DataFrame) -> str:
    """One line for the run's notes: how many parameters the Monte Carlo
    validates, and whether the others miss only by its own numerical noise."""
    failed = frame.filter(~pl.col("validated"))
    text = f"Monte Carlo (GUM Supplement 1) validates the first-order uncertainty of {frame.height - failed.height} of {frame.height} parameters"
    if failed.height:
        excess = failed.select(pl.max_horizontal("d_low", "d_high") - pl.col("tolerance")).to_series()
        noise = int((excess <= 2 * failed["endpoint_numerical_u"]).sum())
        bound = "twice the Monte Carlo's own numerical uncertainty"
        if failed.height == 1:
            text += f"; the other one misses the tolerance by {'less' if noise else 'more'} than {bound}"
        elif noise == failed.height:
            text += f"; the other {failed.height} miss the tolerance by less than {bound}"
        else:
            text += f"; {noise} of the other {failed.height} {'misses' if noise == 1 else 'miss'} the tolerance by less than {bound}"
    return text + " (monte_carlo.parquet)"
