"""Plots for people: the frequency response in the style of Gaitan & Geist
2021 Fig. 6 (each parameter's deviation from the static result against the
rotation rate, with standard uncertainties: the rate-to-DC differences carry no
degrees of freedom of their own, so no coverage factor is claimed) and Fig. 7 (the offset
change with its omega^2 fit). Agg backend, no global pyplot state, written
atomically; the same table gives the same PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from rotcal.model.physics import INTRINSIC
from rotcal.tables import atomic_write

PANELS = (
    ("sensitivity_ratio", "({p}(f) / {p}(DC) - 1) / ppm", 1e6, -1.0),
    ("angle_deviation", "({p}(f) - {p}(DC)) / mdeg", 1e3, 0.0),
    ("offset_change", "({p}(f) - {p}(DC)) / {unit}", 1.0, 0.0),
)


def frequency_response_png(frame: pl.DataFrame, path: Path, title: str) -> Path | None:
    """Nine panels (sensitivities, angles, offsets) from a
    ``frequency_response`` table, titled with its model; None (nothing
    written) when it has no rates."""
    per_rate = frame.filter(pl.col("rate_hz").is_not_null())
    if per_rate.is_empty():
        return None
    fig = Figure(figsize=(11, 8.5), dpi=100)
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 3)
    rates = np.array(sorted(set(per_rate["rate_hz"].to_list())))
    curve = np.geomspace(rates.min() / 1.5, rates.max() * 1.5, 200)
    for row, (quantity, label, scale, shift) in enumerate(PANELS):
        for col in range(3):
            param = INTRINSIC[3 * row + col]
            ax = axes[row, col]
            part = per_rate.filter((pl.col("quantity") == quantity) & (pl.col("parameter") == param)).sort("rate_hz")
            y = (part["value"].to_numpy() + shift) * scale
            err = part["std_uncertainty"].to_numpy() * scale
            ax.axhline(0.0, color="0.6", lw=0.8)
            ax.errorbar(part["rate_hz"].to_numpy(), y, yerr=err, fmt="o", color="C0", capsize=3, ms=4)
            slope = frame.filter((pl.col("quantity") == "offset_omega2_slope") & (pl.col("parameter") == param)
                                 & (pl.col("axis") == "combined"))
            if quantity == "offset_change" and slope.height:
                ax.plot(curve, slope["value"][0] * (2 * np.pi * curve) ** 2, color="C1", lw=1, label="k omega^2")
                ax.legend(loc="best", fontsize=7, frameon=False)
            ax.set_xscale("log")
            ax.set_xticks(rates, labels=[f"{r:g}" for r in rates])
            ax.minorticks_off()  # log-scale minor ticks cost most of the drawing time
            unit = part["unit"][0] if part.height else ""
            ax.set_title(label.format(p=param, unit=unit), fontsize=9)
            ax.tick_params(labelsize=8)
            if row == 2:
                ax.set_xlabel("rotation rate / Hz", fontsize=9)
    fig.suptitle(f"{title}, {per_rate['model'][0]} model: deviation from the static (DC) result, error bars: standard uncertainty", fontsize=11)
    fig.subplots_adjust(left=0.07, right=0.98, bottom=0.07, top=0.91, wspace=0.3, hspace=0.35)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Software": None}))
