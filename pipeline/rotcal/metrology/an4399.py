"""AN4399 (Pedley 2013) corrections with 6, 12 and 15 parameters, fitted to
static positions of known reference acceleration, per temperature, and
their interpolation in temperature (section 9).

Per channel r (x, y, z) the corrected reading in g is

    G_r = W_r . (u, v, w) + V_r + gamma_r * out_r^3     (Eqs. 9, 35, 67)

with out_r the raw output in the same place (u for x, v for y, w for z);
the 6-parameter model keeps only W_rr and V_r (Eq. 9), the 12-parameter
model the full row (Eq. 35), the 15-parameter model adds gamma (Eq. 67).
Each channel is an ordinary least-squares fit over the M positions
(Eqs. 40 to 48 and 68 to 72, solved as Eq. 34) with P = r^T r, the sum of
squared residuals (Eq. 27). With only the two positions of Eqs. 10 or 15 in
a channel the fit is those closed forms; with more it uses every position,
as section 6 recommends.

Scaling: AN4399 applies W to the factory-calibrated output G_f in g. rotcal
applies it to the raw output as recorded, so the correction needs no hidden
scale factor: ``input_unit`` is the dataset's output unit, W is in g per
input unit (AN4399's W divided by N when the input is in counts), V in g
and gamma in g per input unit cubed; for a DUT that outputs g, W is
AN4399's dimensionless gain matrix.

Which models the positions determine is judged on their references alone
(``undetermined``): a model whose reference design has a column that is a
combination of the others (to ``COLLINEAR``, relative) is skipped with the
coefficient and the position that would fix it; the raw outputs' noise and
offsets break such a degeneracy only by chance (the six faces read -1, 0
and +1 g on each axis, where x^3 = x, so gamma duplicates W_rr). A
determined model with no residual degree of freedom (AN4399's exact
four-position fit) is kept with a warning that nothing judges its scatter.

Uncertainties: the readings, not the references, carry the noise, so each
position's equation has the variance grad' Sigma_k grad (grad = W_r +
3 gamma out_r^2 e_r, Sigma_k the covariance of the position's mean), to
first order; ``lsq.ols`` adds the excess scatter of the residuals (jig and
placement tolerance) and gives the covariance of each channel's
coefficients.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.multiposition import pose_arrays
from rotcal.combine.poses import references
from rotcal.errors import UndeterminedError
from rotcal.fit.lsq import least_squares_solution, ols
from rotcal.model.physics import AXES
from rotcal.tables import conform, schema

COEFFICIENTS = ("W_x", "W_y", "W_z", "V", "gamma")
MODELS = (6, 12, 15)
TEMPERATURE_GAP_C = 2.0  # positions whose temperatures differ by more start a new calibration temperature
COLLINEAR = 1e-6  # a reference column within this (relative) of the others' span is not determined by them


@dataclass(frozen=True, eq=False)
class Correction:
    """One channel's correction at one temperature: coefficients in the
    order ``COEFFICIENTS`` (zero where the model has none) and their 5 x 5
    covariance, AN4399's P, the residual degrees of freedom, the number of
    positions and the excess scatter per position (g)."""

    parameters: int
    channel: str
    temperature_c: float
    coef: np.ndarray
    cov: np.ndarray
    sum_sq_residual: float
    dof: int
    n_positions: int
    excess_std: float

    @property
    def std_uncertainty(self) -> np.ndarray:
        return np.sqrt(np.diag(self.cov))


def model_columns(parameters: int, channel: int) -> list[int]:
    """Which of ``COEFFICIENTS`` a model fits for a channel."""
    return {6: [channel, 3], 12: [0, 1, 2, 3], 15: [0, 1, 2, 3, 4]}[parameters]


def apply_correction(coef: np.ndarray, channel: int, raw: np.ndarray) -> np.ndarray:
    """The corrected reading in g of one channel for raw outputs (n, 3)."""
    return raw @ coef[:3] + coef[3] + coef[4] * raw[:, channel] ** 3


def fit_channel(raw: np.ndarray, reference: np.ndarray, channel: int, parameters: int,
                raw_cov: np.ndarray | None = None, temperature_c: float = float("nan")) -> Correction:
    """One channel's AN4399 fit to positions with raw means ``raw`` (M, 3)
    and the reference component ``reference`` (M,) in g.

    Raises ``UndeterminedError`` when the positions do not determine the
    model's coefficients.
    """
    cols = model_columns(parameters, channel)
    full = np.column_stack([raw, np.ones(len(raw)), raw[:, channel] ** 3])
    design = full[:, cols]
    solution = least_squares_solution(design)  # one factorisation for both fits: their designs are the same
    coef = np.zeros(5)
    coef[cols] = solution.coef(reference)[:, 0]
    noise = None
    if raw_cov is not None:
        grad = np.tile(coef[:3], (len(raw), 1))
        grad[:, channel] += 3.0 * coef[4] * raw[:, channel] ** 2
        noise = np.einsum("ki,kij,kj->k", grad, raw_cov, grad)[:, None, None]
    fit = ols(design, reference, noise, solution)
    cov = np.zeros((5, 5))
    cov[np.ix_(cols, cols)] = fit.cov
    excess = float(np.sqrt(fit.excess_cov[0, 0])) if np.isfinite(fit.excess_cov[0, 0]) else float("nan")
    return Correction(parameters, AXES[channel], temperature_c, coef, cov, float(fit.sum_sq_residual[0]),
                      fit.dof, len(raw), excess)


def undetermined(reference: np.ndarray, parameters: int) -> str | None:
    """Why positions with references ``reference`` (M, 3) in g do not
    determine a model's coefficients, naming the last coefficient (in
    ``COEFFICIENTS`` order) whose column the others span and the positions that would fix it; None when
    they do (or when the count alone falls short: ``ols`` says so)."""
    n = len(reference)
    for r in range(3):
        cols = model_columns(parameters, r)
        if n < len(cols):
            return None
        design = np.column_stack([reference, np.ones(n), reference[:, r] ** 3])[:, cols]
        norm = np.linalg.norm(design, axis=0)
        unit = design / np.where(norm > 0, norm, 1.0)
        # a column's distance from the others' span is at least the smallest singular value: well
        # above COLLINEAR, no column is spanned and the per-column projections need not be formed
        if np.linalg.svd(unit, compute_uv=False)[-1] >= 2 * COLLINEAR:
            continue
        for j, col in reversed(list(enumerate(cols))):  # the model's extensions first: gamma, then the cross terms
            others = np.delete(unit, j, axis=1)
            rest = unit[:, j] - others @ np.linalg.lstsq(others, unit[:, j], rcond=None)[0]
            if np.linalg.norm(rest) >= COLLINEAR:
                continue
            name = COEFFICIENTS[col]
            fix = (f"positions where {AXES[r]} reads other levels than -1, 0 and +1 g (tilted, e.g. 45 degrees)"
                   if name == "gamma" else f"positions with gravity along {AXES[col]}" if col < 3
                   else "positions of other references")
            return f"the positions do not determine {name} of channel {AXES[r]} (its column is a combination of the others); {fix} would"
    return None


def temperature_groups(temperature_c: np.ndarray, gap_c: float = TEMPERATURE_GAP_C) -> np.ndarray:
    """Group positions into calibration temperatures: sorted temperatures
    more than ``gap_c`` apart start a new group; positions without a
    temperature form group -1."""
    group = np.full(temperature_c.size, -1, np.int64)
    known = np.flatnonzero(np.isfinite(temperature_c))
    order = known[np.argsort(temperature_c[known], kind="stable")]
    group[order] = np.cumsum(np.r_[0, np.diff(temperature_c[order]) > gap_c])
    return group


def fit_corrections(raw: np.ndarray, reference: np.ndarray, raw_cov: np.ndarray | None = None,
                    temperature_c: np.ndarray | None = None,
                    models: tuple[int, ...] = MODELS) -> tuple[list[Correction], list[str]]:
    """Every model and channel at every calibration temperature; models the
    positions cannot determine become warnings."""
    temps = np.full(len(raw), np.nan) if temperature_c is None else np.asarray(temperature_c, float)
    groups = temperature_groups(temps)
    out, warnings = [], []
    for grp in np.unique(groups):
        at = groups == grp
        t_c = float(np.mean(temps[at])) if grp >= 0 else float("nan")
        where = f" at {t_c:.1f} degC" if grp >= 0 else ""
        for parameters in models:
            why = undetermined(reference[at], parameters)
            if why is not None:
                warnings.append(f"AN4399 {parameters}-parameter correction{where} skipped: {why}")
                continue
            if at.sum() == len(model_columns(parameters, 0)):
                warnings.append(f"AN4399 {parameters}-parameter correction{where}: an exact fit to {at.sum()} positions, "
                                "no residual degree of freedom to judge its scatter (uncertainty not determined)")
            try:
                out += [fit_channel(raw[at], reference[at, r], r, parameters,
                                    None if raw_cov is None else raw_cov[at], t_c) for r in range(3)]
            except UndeterminedError as exc:
                warnings.append(f"AN4399 {parameters}-parameter correction{where} not determined: {exc.problem}")
    return out, warnings


def corrections_from_poses(poses: pl.DataFrame, models: tuple[int, ...] = MODELS) -> tuple[list[Correction], list[str]]:
    """AN4399 corrections from a pose table's positions of known reference."""
    known = poses.filter(pl.all_horizontal(pl.col("ref_x", "ref_y", "ref_z").is_not_nan()))
    if known.height == 0:
        return [], []
    m, cov = pose_arrays(known)
    return fit_corrections(m, references(known), cov, known["temperature_c"].to_numpy(), models)


def interpolate(corrections: list[Correction], temperature_c: float, method: str = "piecewise") -> np.ndarray:
    """One (model, channel)'s coefficients at ``temperature_c`` from its
    corrections at two or more temperatures (AN4399 section 9):
    ``piecewise`` linear between neighbouring calibration temperatures
    (Eqs. 83 and 84; beyond the range, the nearest segment extended), or
    ``quadratic`` in temperature (Eqs. 85 to 90; a least-squares quadratic
    through more than three)."""
    ordered = sorted(corrections, key=lambda c: c.temperature_c)
    temps = np.array([c.temperature_c for c in ordered])
    coef = np.array([c.coef for c in ordered])
    if len(ordered) < 2 or not np.all(np.isfinite(temps)):
        raise UndeterminedError("interpolation in temperature needs corrections at two or more temperatures")
    if method == "quadratic":
        return np.array([np.polynomial.polynomial.polyval(temperature_c, p) for p in temperature_polynomials(temps, coef)])
    k = int(np.clip(np.searchsorted(temps, temperature_c) - 1, 0, len(temps) - 2))
    t1, t2 = temps[k], temps[k + 1]
    return (t2 - temperature_c) / (t2 - t1) * coef[k] + (temperature_c - t1) / (t2 - t1) * coef[k + 1]


def temperature_polynomials(temps: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Per column of ``values`` (n_temperatures, k): the coefficients
    (alpha, beta, gamma) of alpha + beta T + gamma T^2 (Eq. 85) through the
    calibration temperatures: Eq. 90 for three, a line (Eq. 83) for two, a
    least-squares quadratic for more."""
    degree = min(2, len(temps) - 1)
    vander = np.vander(temps, degree + 1, increasing=True)
    coef = np.linalg.lstsq(vander, values, rcond=None)[0]
    return np.vstack([coef, np.zeros((2 - degree, values.shape[1]))]).T


def coefficient_units(input_unit: str) -> tuple[str, ...]:
    if input_unit == "g":
        return ("1", "1", "1", "g", "1/g^2")
    return (f"g/{input_unit}",) * 3 + ("g", f"g/{input_unit}^3")


def correction_frame(corrections: list[Correction], dataset: str, input_unit: str) -> pl.DataFrame:
    """The ``correction`` table (docs/outputs.md)."""
    rows = [{"dataset": dataset, "parameters": c.parameters, "channel": c.channel, "temperature_c": c.temperature_c,
             **dict(zip(COEFFICIENTS, c.coef)), "input_unit": input_unit, "sum_sq_residual": c.sum_sq_residual}
            for c in corrections]
    if not rows:
        return schema("correction").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("correction").polars_schema), "correction")


def correction_uncertainty_frame(corrections: list[Correction], dataset: str, input_unit: str) -> pl.DataFrame:
    """Each fitted coefficient with its standard uncertainty and its
    covariance with the channel's other coefficients."""
    units = coefficient_units(input_unit)
    rows = [{"dataset": dataset, "parameters": c.parameters, "channel": c.channel, "temperature_c": c.temperature_c,
             "coefficient": name, "value": c.coef[i], "std_uncertainty": float(np.sqrt(c.cov[i, i])), "unit": units[i],
             "dof": c.dof, "n_positions": c.n_positions, "excess_std_g": c.excess_std, "cov": c.cov[i].tolist()}
            for c in corrections for i, name in enumerate(COEFFICIENTS) if i in model_columns(c.parameters, AXES.index(c.channel))]
    if not rows:
        return schema("correction_uncertainty").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("correction_uncertainty").polars_schema),
                   "correction_uncertainty")


def temperature_frame(corrections: list[Correction], dataset: str, input_unit: str) -> pl.DataFrame:
    """Per model, channel and coefficient: alpha, beta, gamma of Eq. 85
    across the calibration temperatures (only with two or more)."""
    units = coefficient_units(input_unit)
    keyed: dict[tuple[int, str], list[Correction]] = {}
    for c in corrections:
        if np.isfinite(c.temperature_c):
            keyed.setdefault((c.parameters, c.channel), []).append(c)
    rows = []
    for (parameters, channel), group in sorted(keyed.items()):
        if len(group) < 2:
            continue
        group = sorted(group, key=lambda c: c.temperature_c)
        temps = np.array([c.temperature_c for c in group])
        poly = temperature_polynomials(temps, np.array([c.coef for c in group]))
        for i in model_columns(parameters, AXES.index(channel)):
            rows.append({"dataset": dataset, "parameters": parameters, "channel": channel,
                         "coefficient": COEFFICIENTS[i], "alpha": poly[i, 0], "beta": poly[i, 1], "gamma_t": poly[i, 2],
                         "unit": units[i], "n_temperatures": len(group),
                         "t_min_c": float(temps[0]), "t_max_c": float(temps[-1])})
    if not rows:
        return schema("correction_temperature").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("correction_temperature").polars_schema),
                   "correction_temperature")
