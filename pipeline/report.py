"""Report: human-readable summaries of a run (the CLI prints them)."""

from __future__ import annotations

import numpy as np
from rich.table import Table

from pipeline.combine import IntrinsicResult, units
from pipeline.physics import INTRINSIC

COVERAGE_FACTOR = 2.0


def rate_label(rate_hz: float) -> str:
    return "static (DC)" if rate_hz == 0 else f"{rate_hz:g} Hz"


def _digits(u: float) -> int:
    """Decimals that show an expanded uncertainty to two significant digits."""
    if not np.isfinite(u) or u <= 0:
        return 6
    return max(0, 1 - int(np.floor(np.log10(u))))


def summary_table(results: tuple[IntrinsicResult, ...], output_unit: str, title: str) -> Table:
    """The nine parameters per rate: value +- expanded uncertainty (k = 2)."""
    table = Table(title=title, title_justify="left")
    table.add_column("parameter")
    table.add_column("unit")
    for res in results:
        table.add_column(rate_label(res.rate_hz), justify="right")
    for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit))):
        cells = []
        for res in results:
            expanded = COVERAGE_FACTOR * res.std_uncertainty[i]
            d = _digits(expanded)
            cells.append(f"{res.value[i]:.{d}f} ± {expanded:.{d}f}")
        table.add_row(name, unit, *cells)
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
