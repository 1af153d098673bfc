"""Report: human-readable summaries of a run (the CLI prints them)."""

from __future__ import annotations

import numpy as np
import polars as pl
from rich.console import Group
from rich.table import Table
from rich.text import Text

from rotcal.combine.labelled import units
from rotcal.combine.poses import OrthogonalReferenceFit, ReferenceFit
from rotcal.combine.static import StaticReduction
from rotcal.errors import ExitCode
from rotcal.model.calibration import Recommended, rate_calibration
from rotcal.model.physics import INTRINSIC
from rotcal.model.results import IntrinsicResult
from rotcal.report.rounding import gum_text


def rate_label(rate_hz: float) -> str:
    return "static (DC)" if rate_hz == 0 else f"{rate_hz:g} Hz"


def summary_table(results: tuple[IntrinsicResult, ...], output_unit: str, title: str) -> Group:
    """The nine parameters per rate: value +- expanded uncertainty (95 %,
    each value's k from its effective degrees of freedom)."""
    # title and note as lines of their own: a table's title wraps at its width
    table = Table()
    table.add_column("parameter")
    table.add_column("unit")
    for res in results:
        table.add_column(rate_label(res.rate_hz), justify="right")
    for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit))):
        cells = []
        for res in results:
            fixed = res.std_uncertainty[i] == 0.0  # a model's fixed parameter (orthogonal axes: the angles)
            cells.append(f"{res.value[i]:g} (fixed)" if fixed else _expanded(res.value[i], res.expanded_uncertainty[i]))
        table.add_row(name, unit, *cells)
    return Group(Text(title), table, Text(coverage_note(results)))


def coverage_note(results: tuple[IntrinsicResult, ...]) -> str:
    """How U follows from u: one k, or the range of k over the estimated
    (not fixed) values, each k from that value's effective dof."""
    k = np.concatenate([res.coverage_factor[res.std_uncertainty > 0] for res in results]) if results else np.array([])
    k = k[np.isfinite(k)]
    if k.size == 0:
        return "U = k u"
    low, high = f"{k.min():.2f}", f"{k.max():.2f}"
    if low == high:
        return f"U = k u, k = {low} for every value (from each value's effective dof)"
    return f"U = k u, k from each value's effective dof: {low} to {high}"


def _expanded(value: float, expanded: float) -> str:
    return gum_text(value, expanded) if np.isfinite(expanded) else f"{value:.6g}"


def static_fit_summary(static: StaticReduction, output_unit: str) -> str:
    """One line on the static fit: method, positions, residual degrees of
    freedom, noise-only reduced chi-square and excess scatter."""
    fit = static.fit
    n = static.positions.height
    if fit is None:
        return f"no static fit: {n} positions"
    if isinstance(fit, OrthogonalReferenceFit):
        excess = ", ".join(f"{e:.3g}" for e in np.sqrt(np.diag(fit.excess_cov)))
        return (f"orthogonal-axes fit to {n} positions of known reference ({static.frame} frame): residual dof {fit.dof}, "
                f"excess scatter per position (u, v, w) {excess} {output_unit}")
    if isinstance(fit, ReferenceFit):
        excess = ", ".join(f"{e:.3g}" for e in fit.excess_std)
        return (f"12-parameter fit to {n} positions of known reference ({static.frame} frame): residual dof {fit.dof}, "
                f"reduced chi-square of the pose noise {fit.chi2_reduced:.3g}, excess scatter per position "
                f"(u, v, w) {excess} {output_unit}")
    poses = "labelled poses (the labels as approximate directions)" if static.positions["source"][0] == "label" else "still intervals"
    dof = fit.dof
    judged = (f"reduced chi-square of the pose noise {fit.chi2_reduced:.3g}, excess scatter per position {fit.excess_std:.3g} m/s^2"
              if dof else "exactly determined: no residual to judge the scatter by (more poses would)")
    return (f"orientation-free fit (|a| = g_local) to {n} {poses}: residual dof {dof}, {judged}, "
            f"direction spread {fit.direction_spread:.3g}")


def pose_check_table(check: pl.DataFrame, g_local: float, title: str, per_pose_max: int = 12) -> Table:
    """The |a| check: |a| / g_local - 1 with offsets and sensitivities only,
    after the full correction, and held out (the other half's fit); every
    position when there are few, else RMS and largest."""
    table = Table(title=title, title_justify="left")
    columns = {"offsets and sensitivities only": "norm_orthogonal_m_s2", "full correction": "norm_m_s2",
               "held out (fit to the other half)": "norm_held_out_m_s2"}
    dev = {name: check[col].to_numpy() / g_local - 1.0 for name, col in columns.items()}
    if check.height <= per_pose_max:
        table.add_column("pose")
        table.add_column("|a| after (m/s^2, ± u)", justify="right")
        for name in columns:
            table.add_column(f"{name}: |a|/g - 1 (%)", justify="right")
        for k, row in enumerate(check.iter_rows(named=True)):
            label = row["label"] or str(row["pose"])
            table.add_row(label, _expanded(row["norm_m_s2"], row["u_norm_m_s2"]),
                          *(f"{100 * dev[name][k]:+.3f}" if np.isfinite(dev[name][k]) else "-" for name in columns))
        return table
    table.add_column("|a| / g_local - 1")
    table.add_column("positions", justify="right")
    table.add_column("RMS (%)", justify="right")
    table.add_column("largest (%)", justify="right")
    fold = check["fold"].to_numpy()
    rows = {name: d for name, d in dev.items() if not name.startswith("held")}
    held = dev["held out (fit to the other half)"]
    rows["held out: odd positions, fit to the even"] = held[fold == 1]
    rows["held out: even positions, fit to the odd"] = held[fold == 0]
    for name, d in rows.items():
        d = d[np.isfinite(d)]
        if d.size:
            table.add_row(name, str(d.size), f"{100 * np.sqrt(np.mean(d**2)):.4f}", f"{100 * np.abs(d).max():.4f}")
    return table


def matrix_table(frame: pl.DataFrame, title: str) -> Table:
    """The six parameters of a cross-sensitivity matrix, value ± standard
    uncertainty (another laboratory's matrix carries no degrees of freedom
    to give a coverage factor)."""
    table = Table(title=title, title_justify="left")
    for name in ("parameter", "unit", "value ± u"):
        table.add_column(name, justify="right" if name.startswith("value") else "left")
    for row in frame.iter_rows(named=True):
        table.add_row(row["parameter"], row["unit"], _expanded(row["value"], row["std_uncertainty"]))
    return table


def findings_table(findings, title: str) -> Table:
    """The diagnosis findings (detected rows) with their evidence."""
    table = Table(title=title, title_justify="left", show_lines=True)
    for col in ("effect", "where", "evidence", "BIC change"):
        table.add_column(col, overflow="fold")
    for effect, where, evidence, dbic in findings.filter(findings["detected"]).select(
            "effect", "where", "evidence", "delta_bic").iter_rows():
        table.add_row(effect, where, evidence, f"{dbic:+.0f}")
    return table


def recommendation_line(chosen: Recommended) -> str:
    """Which model's results are the calibration (calibration.json), and why."""
    return f"recommended: the {chosen.model} model's results ({chosen.reason}); calibration.json holds them"


def run_summary(dataset: str, output_unit: str, chosen: Recommended, warnings: tuple[str, ...], notes: tuple[str, ...],
                written: tuple) -> dict:
    """``rotcal run --json``: the recommended result per rate (each of the
    nine parameters as calibration.json gives it: value, u, dof, k, U), the
    exit status, warnings, notes and the files written."""
    rates = [{"rate_hz": res.rate_hz, "frame": frame,
              "parameters": [q.to_dict() for q in rate_calibration(res, frame, chosen.model, chosen.reason,
                                                                    output_unit).parameters]}
             for res, frame in zip(chosen.results, chosen.frames)]
    return {"dataset": dataset, "output_unit": output_unit, "exit_status": int(ExitCode.OK), "model": chosen.model,
            "reason": chosen.reason, "rates": rates, "warnings": list(warnings), "notes": list(notes),
            "written": [str(p) for p in written]}
