"""Frequency response: each rotation rate's intrinsic parameters against the
static (DC) result (Gaitan & Geist 2021 Fig. 6), and the offsets' change
with rate fitted in omega^2 (Fig. 7).

Correlation: the DC result and a rate's result come from different
segments, so their noise is independent, but both use the same g_local.
Every quantity here is a function h(p_f, p_0) of the two parameter
vectors, and its uncertainty is propagated with their joint covariance

    C = [[N_f, 0], [0, N_0]] + j j^T u(g)^2,    j = (dp_f/dg, dp_0/dg),

N the noise-only covariances. For a sensitivity ratio s(f) / s(0), g_local
cancels exactly (both are |g r| / g), and so it does here: its gradient is
orthogonal to j. The centripetal acceleration of Fig. 7, the offset change
divided by the DC sensitivity, keeps the correlation of O(0) and s(0),
which come from the same DC fits.

The omega^2 fit: O(f) = O_0 + k omega^2, omega = 2 pi f, weighted least
squares over all rates including DC (independent points), with chi^2 and
its p-value as the test that the change is quadratic in the rate. For the
``centripetal`` effect of docs/effects.md, k = -r . d. Per rotation axis the
fit uses each segment's own offset C (the centripetal vector d differs per
axis); the ``combined`` fit uses the intrinsic offsets O_r.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.combine.labelled import RateSegments, linear_stage, rate_segments
from rotcal.metrology.consistency import chi2_sf
from rotcal.model.physics import AXES, CHANNELS, INTRINSIC
from rotcal.model.results import Failure, IntrinsicResult, intrinsic_jacobian
from rotcal.tables import conform, schema


def _joint_cov(res_f: IntrinsicResult, res_0: IntrinsicResult) -> np.ndarray:
    cov = np.zeros((18, 18))
    cov[:9, :9], cov[9:, 9:] = res_f.noise_cov, res_0.noise_cov
    j = np.concatenate([res_f.g_sensitivity, res_0.g_sensitivity])
    return cov + np.outer(j, j) * res_0.g_uncertainty**2


def _propagate(value: float, grad: np.ndarray, cov: np.ndarray) -> tuple[float, float]:
    return value, float(np.sqrt(max(grad @ cov @ grad, 0.0)))  # rounding can leave a cancelled g part slightly negative


def rate_rows(res_f: IntrinsicResult, res_0: IntrinsicResult, output_unit: str) -> list[dict]:
    """Sensitivity ratios, angle and offset changes, and centripetal
    accelerations (offset change / DC sensitivity) of one rate against DC."""
    cov, pf, p0 = _joint_cov(res_f, res_0), res_f.value, res_0.value
    omega = 2 * np.pi * res_f.rate_hz
    rows = []

    def add(quantity: str, i: int, value: float, grad: np.ndarray, unit: str, null: float) -> None:
        v, u = _propagate(value, grad, cov)
        rows.append({"quantity": quantity, "parameter": INTRINSIC[i], "axis": "", "rate_hz": res_f.rate_hz,
                     "omega_rad_s": omega, "value": v, "std_uncertainty": u, "unit": unit,
                     "z": (v - null) / u if u > 0 else np.nan})

    for r in range(3):
        grad = np.zeros(18)
        grad[r], grad[9 + r] = 1 / p0[r], -pf[r] / p0[r] ** 2
        add("sensitivity_ratio", r, pf[r] / p0[r], grad, "1", 1.0)
    for i in range(3, 6):
        grad = np.zeros(18)
        grad[i], grad[9 + i] = 1.0, -1.0
        add("angle_deviation", i, pf[i] - p0[i], grad, "deg", 0.0)
    for r in range(3):
        i = 6 + r
        grad = np.zeros(18)
        grad[i], grad[9 + i] = 1.0, -1.0
        add("offset_change", i, pf[i] - p0[i], grad, output_unit, 0.0)
        change = pf[i] - p0[i]
        grad = grad / p0[r]
        grad[9 + r] = -change / p0[r] ** 2
        add("centripetal_acceleration", i, change / p0[r], grad, "m/s^2", 0.0)
    return rows


def omega2_fit(omega: np.ndarray, offset: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Weighted least squares of offset = O_0 + k omega^2: (coefficients
    (O_0, k), their covariance, chi^2, dof)."""
    x = np.column_stack([np.ones_like(omega), omega**2])
    w = 1.0 / u**2
    cov = np.linalg.inv(x.T @ (w[:, None] * x))
    beta = cov @ x.T @ (w * offset)
    chi2 = float(np.sum(w * (offset - x @ beta) ** 2))
    return beta, cov, chi2, omega.size - 2


def _slope_rows(axis: str, r: int, omega: np.ndarray, offset: np.ndarray, u: np.ndarray, cov_s0: np.ndarray,
                res_0: IntrinsicResult, output_unit: str) -> list[dict]:
    """The omega^2 slope k of one channel's offsets, and q = k / s(0), the
    slope of the centripetal acceleration (m). ``cov_s0`` is each point's
    covariance with s(0) (nonzero for DC points, which come from the fits
    that give s(0)): Var(q) = (Var(k) + q^2 Var(s0) - 2 q Cov(k, s0)) / s0^2."""
    if omega.size < 2 or np.unique(omega).size < 2 or np.any(u <= 0):
        return []
    beta, cov, chi2, dof = omega2_fit(omega, offset, u)
    k, u_k = beta[1], np.sqrt(cov[1, 1])
    s0 = res_0.value[r]
    q = k / s0
    weights = (cov @ np.column_stack([np.ones_like(omega), omega**2]).T / u**2)[1]  # k = weights . offset
    u_q = np.sqrt((u_k**2 + q**2 * res_0.cov[r, r] - 2 * q * np.sum(weights * cov_s0)) / s0**2)
    base = {"parameter": INTRINSIC[6 + r], "axis": axis, "rate_hz": None, "omega_rad_s": None,
            "chi2": chi2, "dof": dof, "p_value": chi2_sf(chi2, dof) if dof > 0 else np.nan}
    return [
        {**base, "quantity": "offset_omega2_slope", "value": k, "std_uncertainty": u_k,
         "unit": f"{output_unit}/(rad/s)^2", "z": k / u_k},
        {**base, "quantity": "acceleration_omega2_slope", "value": q, "std_uncertainty": u_q, "unit": "m", "z": q / u_q},
    ]


def _static_offset_cov_with_s0(fits: pl.DataFrame, g_local: float, rates: RateSegments | None) -> dict[int, np.ndarray]:
    """Cov(C_kr, s_r(0)) for every static segment k and channel r: the
    static offsets and the DC sensitivities come from the same fits."""
    dc = dict(rate_segments(fits) if rates is None else rates).get(0.0)
    stage = linear_stage(0.0, dc) if dc else None
    if stage is None or isinstance(stage, Failure):
        return {}
    jac = intrinsic_jacobian(stage.state, g_local)[1][:3] @ stage.L
    cross = stage.cov @ jac.T  # (coefficients, 3)
    return {seg.segment: np.array([cross[9 * k + 3 * r, r] for r in range(3)]) for k, seg in enumerate(stage.segments)}


def frequency_response_frame(results: list[IntrinsicResult], fits: pl.DataFrame, dataset: str, output_unit: str,
                             model: str, segments_by_rate: RateSegments | None = None) -> pl.DataFrame:
    """The ``frequency_response`` table of ``model``'s ``results`` (empty
    without a DC result); the per-axis offset slopes from the segment ``fits``
    (``segments_by_rate``: their ``rate_segments`` when the caller has them)."""
    by_rate = {res.rate_hz: res for res in results}
    res_0 = by_rate.get(0.0)
    rows: list[dict] = []
    if res_0 is not None:
        rates = [res for res in results if res.rate_hz != 0.0]
        for res in rates:
            rows += rate_rows(res, res_0, output_unit)
        ordered = [res_0] + rates
        omega = 2 * np.pi * np.array([res.rate_hz for res in ordered])
        for r in range(3):
            offset = np.array([res.value[6 + r] for res in ordered])
            u = np.array([res.std_uncertainty[6 + r] for res in ordered])
            cov_s0 = np.where(omega == 0, res_0.cov[6 + r, r], 0.0)
            rows += _slope_rows("combined", r, omega, offset, u, cov_s0, res_0, output_unit)
        static_cov = _static_offset_cov_with_s0(fits, res_0.g_local, segments_by_rate)
        ok = fits.filter((pl.col("status") == "ok") & pl.col("kind").is_in(["static", "rotation"]))
        # one pass to numpy, then masks: a polars filter per (axis, channel) cost more than the fits
        axis_of, channel_of = np.array(ok["axis"].to_list()), np.array(ok["channel"].to_list())
        segment, rate, offset, u_offset = ok["segment"].to_numpy(), ok["rate_hz"].to_numpy(), ok["C"].to_numpy(), ok["u_C"].to_numpy()
        for axis in AXES:
            for r, channel in enumerate(CHANNELS):
                at = (axis_of == axis) & (channel_of == channel)
                cov_s0 = np.array([static_cov.get(seg, np.zeros(3))[r] for seg in segment[at].tolist()])
                rows += _slope_rows(axis, r, 2 * np.pi * rate[at], offset[at], u_offset[at], cov_s0, res_0, output_unit)
    if not rows:
        return schema("frequency_response").empty()
    frame = pl.DataFrame([{"dataset": dataset, "model": model, "chi2": None, "dof": None, "p_value": None, **row} for row in rows],
                         schema_overrides=schema("frequency_response").polars_schema, strict=False)
    return conform(frame, "frequency_response")
