"""The Allan deviation of each channel's residuals with its fitted noise
model (IEEE Std 1293-2018 Annex A's plot): points with their chi-square
intervals (68 %, the estimate's own degrees of freedom), the model's curve
and its terms. Agg backend, written atomically; the same model gives the
same PNG."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from scipy.special import chdtri  # chi-square quantiles without scipy.stats (0.2 s of every worker's start)

from rotcal.noise import NoiseModel
from rotcal.tables import atomic_write


def allan_png(model: NoiseModel, path: Path, title: str) -> Path | None:
    """One panel per channel with an Allan variance; None when none has one."""
    shown = [ch for ch in model.channels if ch.allan.tau_s.size]
    if not shown:
        return None
    fig = Figure(figsize=(4.2 * len(shown), 4.2), dpi=100)
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(1, len(shown), sharey=True))
    for ax, ch in zip(axes, shown):
        av = ch.allan
        low = np.sqrt(av.avar * av.edf / chdtri(av.edf, 0.16))
        high = np.sqrt(av.avar * av.edf / chdtri(av.edf, 0.84))
        ax.errorbar(av.tau_s, av.adev, yerr=[av.adev - low, high - av.adev], fmt="o", ms=3, color="k",
                    label="residuals")
        if ch.terms:
            tau = np.geomspace(av.tau_s[0], av.tau_s[-1], 200)
            ax.loglog(tau, np.sqrt(np.maximum(ch.model_avar(tau), 1e-300)), color="C3", label="model")
            text = "\n".join(f"{t.term.replace('_', ' ')}{f' {t.index}' if t.term.startswith('gauss') else ''}: "
                             f"{t.value:.3g} ± {t.u:.2g}" for t in ch.terms if t.value > 2 * t.u)
            ax.text(0.03, 0.03, text, transform=ax.transAxes, fontsize=7, va="bottom")
        else:
            ax.text(0.03, 0.03, ch.reason or "", transform=ax.transAxes, fontsize=7, va="bottom", wrap=True)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("averaging time tau / s")
        ax.set_title(ch.channel)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel(f"Allan deviation / {model.output_unit}")
    axes[0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", metadata={"Software": None}))
