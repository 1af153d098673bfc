"""Gaitan & Geist 2021's own estimators, beside rotcal's full-vector
reconstruction (Geist 2017 Eqs. 10 to 16).

Sensitivities from the sine amplitudes, Eqs. 8 to 10 with the subscripts
corrected (docs/method.md, "Printing errors in the papers"; Eq. 8 also prints
B^z_uz for B^x_uz): for rotation
about axis s a channel's amplitude is A^2 + B^2 = g^2 (|r|^2 - r_s^2), so the
sum over the three axes is 2 g^2 |r|^2 and

    s_r = sqrt(sum_s (A_rs^2 + B_rs^2) / 2) / g,

exact whatever the mount. Angles from phase differences, Eqs. 11 to 16:
writing a channel's signal A sin(theta) + B cos(theta) as
sqrt(A^2 + B^2) sin(theta + p), its phase is p = atan2(B, A). The paper's
atan(B / A) is ambiguous by 180 degrees and was resolved by plotting; here
atan2 takes the quadrant from the signs of A and B (A = -g r_a, B = g r_b,
docs/conventions.md), and the wrapped phase difference d of two channels,
in (-180, 180], has |d| equal to the angle between the projections of the
two responsivity vectors on the plane perpendicular to the rotation axis
((A, B) = g (-r_a, r_b) is a reflection of (r_a, r_b), which keeps angles).
An intrinsic angle lies in (0, 180) degrees, so phi = |d|. Gaitan pairs the
two large signals of each rotation: v, w about x (phi_vw, Eq. 14); w, u
about y (phi_wu, Eq. 15); u, v about z (phi_uv, Eq. 16). The angle between
projections equals the intrinsic angle only when the third components of
both vectors vanish, i.e. for a perfect mount; the error grows with the
square of the misalignment.

Uncertainties are propagated to first order with the full covariance of
the segments' coefficients (A-B correlation of a non-whole number of turns,
correlation between channels) and g_local; the printed Eqs. 18 to 20 (too
large by sqrt(2) g, docs/method.md) and 24 to 27 (independent A, B and phases;
subscripts corrected: Eq. 25 prints SE{A^y_vx} for SE{A^z_vx}, Eq. 27
SE{A^y_uz} inside its last denominator) are evaluated beside them for
comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.labelled import LinearStage, RateSegments, linear_stage, rate_segments, units
from rotcal.model.physics import AXES, INTRINSIC
from rotcal.model.results import Failure, intrinsic_jacobian
from rotcal.tables import conform, schema

# rotation axis -> (channel i, channel j) with phi = |phase_j - phase_i|, and the parameter's index in INTRINSIC
PHASE_PAIRS = {"z": (0, 1, 3), "x": (1, 2, 4), "y": (2, 0, 5)}


@dataclass(frozen=True, eq=False)
class GaitanResult:
    """Gaitan's six estimates (s_u, s_v, s_w, phi_uv, phi_vw, phi_wu) of one
    rate: value, Jacobian with respect to the stacked segment coefficients
    and to g_local, and the printed standard errors (Eqs. 18 to 20, 24 to 27)."""

    rate_hz: float
    value: np.ndarray
    jac: np.ndarray
    jac_g: np.ndarray
    printed_u: np.ndarray


def _ab(stage: LinearStage, k: int, r: int) -> tuple[int, int]:
    """Indices of A and B of channel r, segment k, in the stacked coefficients."""
    return 9 * k + 3 * r + 1, 9 * k + 3 * r + 2


def gaitan_rate(stage: LinearStage, g_local: float) -> GaitanResult | None:
    """Eqs. 8 to 16 on one rate's fits; None unless exactly one segment per axis."""
    axes = [s.axis for s in stage.segments]
    if sorted(axes) != list(AXES):
        return None
    c, se = stage.coef, np.sqrt(np.diag(stage.cov))
    value, jac, jac_g, printed = np.zeros(6), np.zeros((6, c.size)), np.zeros(6), np.zeros(6)
    for r in range(3):  # Eqs. 8 to 10
        idx = [i for k in range(3) for i in _ab(stage, k, r)]
        s = np.sqrt(np.sum(c[idx] ** 2) / 2) / g_local
        value[r], jac_g[r] = s, -s / g_local
        jac[r, idx] = c[idx] / (2 * g_local**2 * s)
        printed[r] = np.sqrt(np.sum((c[idx] * se[idx]) ** 2) / (2 * s**2)) / g_local  # Eqs. 18 to 20 as printed
    for k, axis in enumerate(axes):  # Eqs. 11 to 16
        i, j, row = PHASE_PAIRS[axis]
        (ai, bi), (aj, bj) = _ab(stage, k, i), _ab(stage, k, j)
        d = np.angle(np.exp(1j * (np.arctan2(c[bj], c[aj]) - np.arctan2(c[bi], c[ai]))))
        value[row] = np.degrees(abs(d))
        sign = np.degrees(1.0) * np.sign(d)
        for a, b, side in ((ai, bi, -1.0), (aj, bj, 1.0)):
            amp2 = c[a] ** 2 + c[b] ** 2
            jac[row, a] = sign * side * -c[b] / amp2
            jac[row, b] = sign * side * c[a] / amp2
        printed[row] = np.degrees(np.sqrt(sum(((c[a] * se[b]) ** 2 + (c[b] * se[a]) ** 2) / (c[a] ** 2 + c[b] ** 2) ** 2
                                              for a, b in ((ai, bi), (aj, bj)))))  # Eqs. 24 to 27
    return GaitanResult(stage.rate_hz, value, jac, jac_g, printed)


def gaitan_frame(fits: pl.DataFrame, g_local: float, g_uncertainty: float, dataset: str, output_unit: str,
                 by_rate: RateSegments | None = None) -> pl.DataFrame:
    """The ``gaitan_estimators`` table: Gaitan's estimates, their honest
    uncertainties and the printed ones, beside the full-vector estimates of
    ``intrinsic.parquet``, with the difference and its uncertainty (both
    come from the same coefficients, so the difference's covariance is
    propagated through the difference of the two Jacobians)."""
    rows = []
    for rate, segs in rate_segments(fits) if by_rate is None else by_rate:  # the caller's, when it has them
        stage = linear_stage(rate, segs)
        if isinstance(stage, Failure):
            continue
        gr = gaitan_rate(stage, g_local)
        if gr is None:
            continue
        full, jac_full, jac_g_full = intrinsic_jacobian(stage.state, g_local)
        jac_full = (jac_full @ stage.L)[:6]
        u_noise = np.sqrt(np.einsum("ij,jk,ik->i", gr.jac, stage.cov, gr.jac))
        u = np.sqrt(u_noise**2 + (gr.jac_g * g_uncertainty) ** 2)
        u_full = np.sqrt(np.einsum("ij,jk,ik->i", jac_full, stage.cov, jac_full) + (jac_g_full[:6] * g_uncertainty) ** 2)
        jd, jd_g = gr.jac - jac_full, gr.jac_g - jac_g_full[:6]
        u_diff = np.sqrt(np.einsum("ij,jk,ik->i", jd, stage.cov, jd) + (jd_g * g_uncertainty) ** 2)
        source = {row: axis for axis, (_, _, row) in PHASE_PAIRS.items()}
        for p, (name, unit) in enumerate(zip(INTRINSIC[:6], units(output_unit))):
            diff = gr.value[p] - full[p]
            rows.append({
                "dataset": dataset, "rate_hz": rate, "parameter": name, "unit": unit,
                "source_axes": source.get(p, ",".join(AXES)),
                "value": gr.value[p], "std_uncertainty": u[p], "u_statistical": u_noise[p],
                "u_printed": gr.printed_u[p], "printed_over_statistical": gr.printed_u[p] / u_noise[p] if u_noise[p] > 0 else np.nan,
                "full_vector_value": full[p], "full_vector_std_uncertainty": u_full[p],
                "difference": diff, "u_difference": u_diff[p], "z_difference": diff / u_diff[p] if u_diff[p] > 0 else np.nan,
            })
    if not rows:
        return schema("gaitan_estimators").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("gaitan_estimators").polars_schema, strict=False), "gaitan_estimators")
