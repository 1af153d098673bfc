"""The certificate's figures, embedded in the page as base64 PNG (a data:
URI, so that the page needs no other file): the |a| check and the
frequency response (``plot.frequency_response_png``, reused where the run
drew it). Agg canvas, no pyplot state, no timestamp: the same tables give
the same bytes."""

from __future__ import annotations

import base64
import io
import tempfile
from pathlib import Path

import numpy as np
import polars as pl
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from rotcal.report.plot import frequency_response_png

MARKERS = {"pose": ("o", "C0"), "dwell": ("s", "C2"), "segment fit": ("D", "C1")}


def data_uri(png: bytes) -> str:
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def norm_figure(check: pl.DataFrame, g_local: float) -> bytes:
    """|a| / g_local - 1 (ppm) of every pose, dwell or segment in the
    order the tables list them, error bars the standard uncertainty where
    the table gives it."""
    fig = Figure(figsize=(10, 3.6), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    deviation = check["deviation_ppm"].to_numpy()
    u = check["u_norm_m_s2"].fill_null(0.0).to_numpy() / g_local * 1e6
    # the axis spans the points with their error bars; a held-out prediction beyond it sits on its edge
    low, high = (deviation - u).min(), (deviation + u).max()
    low, high = low - 0.15 * (high - low + 1), high + 0.15 * (high - low + 1)
    start = 0
    for kind, part in check.group_by("kind", maintain_order=True):
        name = str(kind[0])
        marker, color = MARKERS.get(name, ("o", "C3"))
        x = np.arange(start, start + part.height)
        err = u[start:start + part.height]
        ax.errorbar(x, deviation[start:start + part.height], yerr=err if err.any() else None, fmt=marker,
                    color=color, ms=4, capsize=2, lw=0.8, label=name)
        held = part["held_out_ppm"].fill_null(np.nan).to_numpy()
        if np.isfinite(held).any():
            inside = (held >= low) & (held <= high)
            ax.plot(x[inside], held[inside], "x", color="0.45", ms=4, label=f"{name}, held out (two-fold)")
            beyond = np.isfinite(held) & ~inside
            if beyond.any():
                ax.plot(x[beyond], np.clip(held[beyond], low, high), "x", color="C3", ms=6, mew=1.5, clip_on=False,
                        label="held out, beyond the axis (on its edge)")
        start += part.height
    ax.set_ylim(low, high)
    ax.axhline(0.0, color="0.6", lw=0.8)
    ax.set_xlabel("pose, dwell or segment (in the order of the tables)", fontsize=9)
    ax.set_ylabel("|a| / g_local - 1 (ppm)", fontsize=9)
    ax.set_title(f"|a| check against g_local = {g_local:g} m/s^2, error bars: standard uncertainty", fontsize=10)
    ax.tick_params(labelsize=8)
    ax.legend(fontsize=8, frameon=False, loc="best")
    fig.subplots_adjust(left=0.08, right=0.98, bottom=0.15, top=0.9)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", metadata={"Software": None})
    return buffer.getvalue()


def frequency_response_figure(run_dir: Path, response: pl.DataFrame, dataset: str) -> bytes | None:
    """The run's frequency-response PNG where it drew one, else drawn from its table; None without rates."""
    drawn = run_dir / "frequency_response.png"
    if drawn.is_file():
        return drawn.read_bytes()
    with tempfile.TemporaryDirectory() as scratch:
        path = frequency_response_png(response, Path(scratch) / "frequency_response.png", dataset)
        return None if path is None else path.read_bytes()
