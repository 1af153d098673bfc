"""The diagnosis report of a static recording (``diagnose.static``):
``report.md`` with the findings, the effect parameters, the detection limit
of every parameter tested and found absent, and the refined against the
baseline intrinsic parameters (the tables of ``report.diagnosis``); per
finding, a figure of the poses' residuals against what the effect follows
(the channel's output, time or temperature), before and after modelling it."""

from __future__ import annotations

from pathlib import Path

from rotcal.diagnose.static import StaticDiagnosis, limit_text
from rotcal.model.results import IntrinsicResult
from rotcal.report.diagnosis import _comparison, _pyplot, _save, _table, findings_section, found_line
from rotcal.report.rounding import gum_round
from rotcal.tables import atomic_write


def residual_figure(diag: StaticDiagnosis, name: str, path: Path) -> str:
    """The poses' weighted residuals (residual over its standard
    uncertainty) against what ``name`` follows, without it and with the
    final model; returns what they are drawn against."""
    label, x, r = diag.against[name]
    fig, axes = _pyplot().subplots(2, 1, figsize=(7, 5), sharex=True)
    for ax, residuals, title in ((axes[0], diag.before[name], f"without {name}"), (axes[1], diag.after, "final model")):
        ax.plot(x, diag.channel(residuals, r), "o", ms=4, color="tab:blue")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("residual / u")
        ax.set_title(title, fontsize=9)
    axes[1].set_xlabel(label)
    what = "|a| - g_local" if diag.method == "orientation-free" else f"channel {'uvw'[r]}"
    fig.suptitle(f"{name}: {what} per pose", fontsize=10)
    fig.tight_layout()
    _save(fig, path)
    return label


def write_static_report(diag: StaticDiagnosis, baseline: tuple[IntrinsicResult, ...], dataset: str,
                        output_unit: str, out: Path, draw: bool = True) -> Path:
    """Write ``report.md`` into ``out``, and its figures when ``draw``."""
    findings = diag.findings
    found = findings.filter(findings["detected"])
    what = ("|a| = g_local residuals of the orientation-free fit" if diag.method == "orientation-free"
            else "vector residuals against the poses' known references")
    lines = [f"# Diagnosis of {dataset}", "",
             f"Static recording: the {what}, {diag.poses} poses, tested against each channel's output "
             "(nonlinearity), time (offset drift) and temperature (thermal, when logged).", ""]
    if found.height == 0:
        lines.append("No finding: the poses agree with the papers' model within their noise.")
    else:
        lines.append(found_line(found))
    lines += findings_section(findings, output_unit)
    if diag.parameters.height:
        lines += ["## Effect parameters", "",
                  _table([[e, p, *gum_round(v, u), unit] for e, p, v, u, unit in diag.parameters.select(
                      "effect", "parameter", "value", "std_uncertainty", "unit").iter_rows()],
                         ["effect", "parameter", "value", "standard uncertainty", "unit"]), ""]
    if diag.limits:
        lines += ["## Detection limits", "",
                  "The size of each parameter tested and not found at which its expected test statistic reaches "
                  "the threshold (50 % power at the false-alarm rate), with these poses and this noise:", "",
                  _table([[name, limit_text(size)] for name, size in diag.limits.items()], ["parameter", "size"]), ""]
    lines += ["## Refined against baseline intrinsic parameters", "", _comparison(baseline, diag.refined, output_unit)]
    if draw and diag.before:
        (out / "figures").mkdir(parents=True, exist_ok=True)
        lines += ["## Figures", ""]
        for name in sorted(diag.before):
            label = residual_figure(diag, name, out / "figures" / f"poses_{name}.png")
            lines += [f"The poses' residuals against {label}, before and after modelling {name}:", "",
                      f"![{name}](figures/poses_{name}.png)", ""]
    return atomic_write(out / "report.md", lambda tmp: tmp.write_text("\n".join(lines)))
