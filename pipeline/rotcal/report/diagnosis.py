"""The diagnosis report of one dataset: ``report.md`` with PNG figures.

For every finding, the residuals of the segment where it lies most, before
(the model without it) and after (the final model), as binned means so that
structure below the noise of one sample shows; the offsets of every rotation
against w^2 before and after the modelled centripetal acceleration (Gaitan
2021 Fig. 7); the findings table with one sentence each; the refined
against the baseline parameters.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from rotcal.combine.labelled import units
from rotcal.diagnose import Diagnosis
from rotcal.model.physics import AXES, CHANNELS, INTRINSIC
from rotcal.model.results import IntrinsicResult
from rotcal.report.rounding import gum_round, gum_text
from rotcal.tables import atomic_write

COLORS = ("tab:red", "tab:green", "tab:blue")


def _pyplot():
    """matplotlib's pyplot on the Agg backend, imported when a figure is
    drawn: a batch writes report.md without figures, and each worker would
    otherwise spend about a second importing it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png", metadata={"Software": None}))
    _pyplot().close(fig)


def _binned(t: np.ndarray, r: np.ndarray, bins: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    edges = np.linspace(t.min(), t.max(), bins + 1)
    which = np.clip(np.searchsorted(edges, t, side="right") - 1, 0, bins - 1)
    count = np.bincount(which, minlength=bins)
    mean = np.bincount(which, weights=r, minlength=bins) / np.maximum(count, 1)
    sq = np.bincount(which, weights=r * r, minlength=bins) / np.maximum(count, 1)
    err = np.sqrt(np.maximum(sq - mean**2, 0) / np.maximum(count - 1, 1))
    centre = 0.5 * (edges[1:] + edges[:-1])
    keep = count > 1
    return centre[keep], mean[keep], err[keep]


def residual_figure(diag: Diagnosis, name: str, path: Path, output_unit: str) -> str:
    """Residuals before and after modelling ``name`` in the segment where
    modelling it changed them most; returns that segment's description."""
    obs, final = diag.final.obs, diag.final
    before, after = diag.before[name], final.residuals
    use = final.use
    gain = np.zeros(int(obs.segment.max()) + 1)
    np.add.at(gain, obs.segment, ((before**2 - after**2) * use).sum(axis=1))
    gain[np.setdiff1d(np.arange(gain.size), obs.segment)] = -np.inf  # numbers of segments not modelled (dwells)
    seg = int(np.argmax(gain))
    at = obs.segment == seg
    t = obs.motion.t_s[at]
    fig, axes = _pyplot().subplots(2, 1, figsize=(8, 5), sharex=True)
    for ax, resid, title in ((axes[0], before, f"without {name}"), (axes[1], after, "final model")):
        for r, c in enumerate(CHANNELS):
            keep = use[at, r]
            if not keep.any():  # clipped throughout this segment: nothing of the channel to draw
                continue
            x, mean, err = _binned(t[keep], resid[at, r][keep])
            ax.errorbar(x - t[0], mean, err, color=COLORS[r], lw=1, ms=2, marker="o", label=c)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel(f"mean residual ({output_unit})")
        ax.set_title(title, fontsize=9)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8, ncol=3)
    axes[1].set_xlabel(f"time in segment {seg} (s)")
    rate = obs.motion.rate_hz[at][0]
    where = f"segment {seg}: axis {AXES[obs.motion.axis_idx[at][0]]}, {'static' if rate == 0 else f'{rate:g} Hz'}"
    fig.suptitle(f"{name}: binned residuals, {where}", fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    return where


def offsets_figure(diag: Diagnosis, fits: pl.DataFrame, path: Path, output_unit: str) -> None:
    """Each rotation segment's offset C minus the static offset of its axis,
    against w^2, before and after the modelled centripetal acceleration."""
    final, layout = diag.final, diag.final.layout
    values = layout.values(final.beta, final.active)
    ok = fits.filter(pl.col("status") == "ok")
    fig, axes = _pyplot().subplots(1, 3, figsize=(11, 3.6), sharey=True)
    for a, axis in enumerate(AXES):
        part = ok.filter(pl.col("axis") == axis)
        static = part.filter(pl.col("rate_hz") == 0)
        ax = axes[a]
        for r, c in enumerate(CHANNELS):
            # the rates the diagnosis modelled (a rate recorded about one axis alone is not among them)
            rot = part.filter((pl.col("rate_hz") != 0) & (pl.col("channel") == c)
                              & pl.col("rate_hz").is_in(final.obs.rates.tolist())).sort("rate_hz")
            if rot.height == 0 or static.filter(pl.col("channel") == c).height == 0:
                continue
            c0 = static.filter(pl.col("channel") == c)["C"][0]
            rates = rot["rate_hz"].to_numpy()
            w2 = (2 * np.pi * rates) ** 2
            change = rot["C"].to_numpy() - c0
            model = np.zeros_like(change)
            d = np.array([values.get(f"centripetal.{axis}.d_{s}_m", 0.0) for s in AXES])
            for k, rate in enumerate(rates):
                f = int(np.flatnonzero(final.obs.rates == rate)[0])
                model[k] = -w2[k] * (layout.responsivity(final.beta)[f, r] @ d) / final.obs.g_local
            ax.plot(w2, change, "o-", color=COLORS[r], label=f"{c} before")
            ax.plot(w2, change - model, "s--", color=COLORS[r], mfc="none", label=f"{c} after")
        ax.set_title(f"rotation about {axis}", fontsize=9)
        ax.set_xlabel("w^2 (rad^2/s^2)")
    axes[0].set_ylabel(f"offset change from static ({output_unit})")
    labelled = next((ax for ax in axes if ax.get_legend_handles_labels()[0]), None)
    if labelled is not None:
        labelled.legend(fontsize=7, ncol=2)
    fig.suptitle("offsets against w^2, before and after modelling the centripetal acceleration", fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def _table(rows: list[list[str]], header: list[str]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(cell.replace("|", "/") for cell in row) + " |" for row in rows]
    return "\n".join(out)


def _comparison(baseline: tuple[IntrinsicResult, ...], refined: tuple[IntrinsicResult, ...], output_unit: str) -> str:
    if not refined:
        return "Nothing was modelled beyond the papers' model: the baseline parameters stand.\n"
    rows = []
    by_rate = {r.rate_hz: r for r in baseline}
    for res in refined:
        base = by_rate[res.rate_hz]
        for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit))):
            diff = res.value[i] - base.value[i]
            rows.append([f"{res.rate_hz:g}", name, gum_text(base.value[i], base.expanded_uncertainty[i]),
                         gum_text(res.value[i], res.expanded_uncertainty[i]),
                         f"{diff / base.std_uncertainty[i]:+.1f}", unit])
    return _table(rows, ["rate (Hz)", "parameter", "baseline (± U, 95 %)", "refined (± U, 95 %)",
                         "shift / u(baseline)", "unit"]) + "\n"


def found_line(found: pl.DataFrame) -> str:
    """The report's one-line summary of the detected findings."""
    return (f"{found.height} finding{'s' if found.height > 1 else ''}: "
            + "; ".join(f"**{e}** ({w})" for e, w in found.select("effect", "where").iter_rows()) + ".")


def findings_section(findings: pl.DataFrame, output_unit: str) -> list[str]:
    """The report's findings table: every effect tested, detected or not, with its evidence."""
    return ["", "## Findings", "",
            _table([[e, "yes" if d else "no", w, ev, f"{b:.3g} -> {a:.3g}", f"{bic:+.0f}"]
                    for e, d, w, ev, b, a, bic in findings.select(
                        "effect", "detected", "where", "evidence", "rms_before", "rms_after", "delta_bic").iter_rows()],
                   ["effect", "detected", "where", "evidence", f"RMS before -> after ({output_unit})", "BIC change"]),
            ""]


def write_report(diag: Diagnosis, fits: pl.DataFrame, baseline: tuple[IntrinsicResult, ...], dataset: str,
                 output_unit: str, out: Path, draw: bool = True) -> Path:
    """Write ``report.md`` into ``out``, and its figures when ``draw``."""
    findings = diag.findings
    found = findings.filter(pl.col("detected"))
    lines = [f"# Diagnosis of {dataset}", ""]
    if found.height == 0:
        lines.append("No finding: the recording agrees with the papers' model within its noise; every catalogue "
                     "effect was tested (table below).")
    else:
        lines.append(found_line(found))
    if diag.final.obs.n < diag.samples_available:
        lines += ["", f"The model used {diag.final.obs.n:,} of the {diag.samples_available:,} samples of the fitted "
                  "segments (long segments thinned evenly, `[diagnosis] max_samples`): effects smaller than the "
                  "thinned data can resolve may go unnamed."]
    if diag.phases is not None and diag.phases.height:
        lines += ["", f"The table angles of {diag.phases.height} rotation segments are reconstructed from their solved "
                  "phases (no angle was recorded); a rate error is not tested, since the fitted rates absorb it."]
    lines += findings_section(findings, output_unit)
    if diag.parameters.height:
        lines += ["## Effect parameters", "",
                  _table([[e, a or "-", p, *gum_round(v, u), unit] for e, a, p, v, u, unit in diag.parameters.select(
                      "effect", "axis", "parameter", "value", "std_uncertainty", "unit").iter_rows()],
                         ["effect", "axis", "parameter", "value", "standard uncertainty", "unit"]), ""]
    lines += ["## Refined against baseline intrinsic parameters", "", _comparison(baseline, diag.refined, output_unit)]
    if draw:
        lines += _figures(diag, fits, out / "figures", output_unit)
    return atomic_write(out / "report.md", lambda tmp: tmp.write_text("\n".join(lines)))


def _figures(diag: Diagnosis, fits: pl.DataFrame, figures: Path, output_unit: str) -> list[str]:
    """Draw the report's figures into ``figures``; the report's lines that show them."""
    figures.mkdir(parents=True, exist_ok=True)
    lines = ["## Figures", ""]
    for k, name in enumerate(sorted(diag.before)):
        file = f"residuals_{k}_{name.replace(' ', '_').replace(':', '')}.png"
        where = residual_figure(diag, name, figures / file, output_unit)
        lines += [f"Residuals before and after modelling {name} ({where}):", "", f"![{name}](figures/{file})", ""]
    if diag.final.obs.motion.rotating.any():
        offsets_figure(diag, fits, figures / "offsets_vs_w2.png", output_unit)
        centripetal = diag.findings.filter(pl.col("detected") & (pl.col("effect") == "centripetal")).height > 0
        caption = ("before and after the modelled centripetal acceleration:" if centripetal else
                   "as fitted: no centripetal acceleration was detected, so none is modelled (a DUT off the axis "
                   "would show offsets growing with w^2):")
        lines += [f"Offsets of the rotation segments against w^2 (Gaitan 2021 Fig. 7), {caption}", "",
                  "![offsets](figures/offsets_vs_w2.png)", ""]
    return lines
