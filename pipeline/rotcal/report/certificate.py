"""The calibration certificate of one dataset: one self-contained HTML page
(``certificate.html``, figures embedded as data: URIs, no other resource),
a view of a run's published files: ``calibration.json`` (the result, read
with ``Calibration.read``) and the Parquet tables beside it, each optional
but the document. Values with their expanded uncertainties are rounded as
GUM 7.2.6 asks (``rounding.gum_round``); the checks and the budget summary
come from ``certificate_checks``, the figures from ``certificate_figures``.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping
from functools import cache
from html import escape
from importlib.resources import files
from pathlib import Path
from string import Template
from typing import TYPE_CHECKING

import polars as pl

from rotcal.errors import InputError
from rotcal.model.calibration import Calibration, Quantity, RateCalibration
from rotcal.model.results import EXPANDED_COVERAGE
from rotcal.report.certificate_checks import main_contributions, norm_check, norm_remark, norm_summary
from rotcal.report.rounding import gum_round, gum_text
from rotcal.tables import atomic_write, schema

if TYPE_CHECKING:
    import pyarrow as pa

CERTIFICATE = "certificate.html"
# the published tables the page reads, each where the run wrote it
TABLES = ("segments", "fits", "dwells", "poses", "diagnosis", "uncertainty_budget", "frequency_response")
KINDS = {"table": "table segments", "static": "static poses", "unlabelled": "unlabelled recording"}
METHODS = {
    "table": "each segment's outputs were fitted with a sine against the table angle (static step sequences and "
             "constant-rate rotations about the table's x, y and z axes), and each rate's responsivity vectors and "
             "offsets combined from those fits (Geist 2017; Gaitan & Geist 2021).",
    "static": "the nine parameters were fitted to the mean outputs of the static poses, the corrected acceleration "
              "of every pose having the magnitude g_local (against the pose's reference direction where the poses "
              "are labelled or on a jig).",
    "unlabelled": "the segments were found in the signals without labels: rotations fitted against their own "
                  "phase (phase-free reduction) and the static rate from the dwells by the orientation-free fit "
                  "(|a| = g_local in every dwell).",
}


def _cell(text: object, cls: str = "") -> str:
    return f'<td class="{cls}">{escape(str(text))}</td>' if cls else f"<td>{escape(str(text))}</td>"


def _table(header: list[str], rows: list[str], cls: str = "") -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in header)
    return f'<table class="{cls}"><thead><tr>{head}</tr></thead><tbody>{"".join(rows)}</tbody></table>'


def _fields(pairs: list[tuple[str, str]]) -> str:
    return _table(["field", "value"], [f"<tr><th>{escape(k)}</th>{_cell(v)}</tr>" for k, v in pairs], "fields")


def _rate_label(rate_hz: float) -> str:
    return "static (DC)" if rate_hz == 0 else f"{rate_hz:g} Hz"


def _dof(q: Quantity) -> str:
    return "∞" if q.dof == float("inf") else f"{q.dof:.0f}"


def read_tables(run_dir: Path) -> dict[str, pl.DataFrame]:
    """The published tables present in ``run_dir`` (absent ones left out); an unreadable one is an input error."""
    tables = {}
    for name in TABLES:
        path = run_dir / f"{name}.parquet"
        if path.is_file():
            try:
                frame = pl.read_parquet(path)
            except (OSError, pl.exceptions.PolarsError) as exc:
                raise InputError(f"cannot read {name}.parquet: {exc}".splitlines()[0], path=path) from None
            missing = [c for c in schema(name).columns if c not in frame.columns]
            if missing:
                raise InputError(f"not rotcal's {name} table: no column {', '.join(missing)}", path=path)
            tables[name] = frame
    return tables


def run_kind(tables: dict[str, pl.DataFrame]) -> str:
    """table, static or unlabelled, from what the run published: poses
    (a static reduction), or segments none of which has a table angle."""
    if "poses" in tables:
        return "static"
    segments = tables.get("segments")
    if segments is not None and segments.height and (segments["angle_source"] == "none").all():
        return "unlabelled"
    return "table"


def identification(cal: Calibration, kind: str) -> str:
    device = [(f"device {k}", "" if v is None else str(v)) for k, v in cal.device.items() if k != "output_unit"]
    fields = _fields([("dataset", cal.dataset), *device, ("output unit", cal.output_unit), ("kind of run", KINDS[kind])])
    inputs = _table(["input file", "bytes", "SHA-256"], [
        f"<tr>{_cell(f['path'])}{_cell(f['bytes'], 'num')}{_cell(f['sha256'], 'hash')}</tr>" for f in cal.inputs])
    return f"<h2>1. Identification</h2>{fields}<h3>Inputs (content hashes)</h3>{inputs}"


def method(cal: Calibration, kind: str) -> str:
    frames = sorted({r.frame for r in cal.rates})
    where = f"the {frames[0]} frame" if len(frames) == 1 else "the frame each rate's results name"
    return ("<h2>2. Method and conventions</h2>"
            f"<p><b>Method:</b> {escape(METHODS[kind])}</p>"
            "<p><b>Conventions</b> (docs/conventions.md): u, v, w are the DUT's output channels and x, y, z the "
            f"axes of the frame of P's rows ({escape(where)}); s is each channel's sensitivity, phi the angles "
            "between the sensitive axes, O the offsets; the calibrated acceleration is a = P (R - O) for a raw "
            "output R. "
            "U = k u with k = t<sub>0.975</sub>(&nu;<sub>eff</sub>) for 95 % coverage (GUM G.4), rounded to two "
            "significant digits of U and the value to the same decimal place (GUM 7.2.6).</p>")


def _span(ks: list[float]) -> str:
    low, high = f"{min(ks):.2f}", f"{max(ks):.2f}"
    return low if low == high else f"{low} to {high}"


def _rate_results(rc: RateCalibration) -> str:
    rows = []
    for q in rc.parameters:
        value, expanded = gum_round(q.value, q.expanded_uncertainty)
        rows.append(f'<tr data-rate="{rc.rate_hz!r}" data-parameter="{escape(q.name)}">{_cell(q.name)}'
                    f'{_cell(value, "num value")}{_cell(expanded, "num U")}{_cell(f"{q.coverage_factor:.2f}", "num k")}'
                    f'{_cell(_dof(q), "num dof")}{_cell(q.unit)}</tr>')
    table = _table(["parameter", "value", "U (95 %)", "k", "ν_eff", "unit"], rows, "results")
    # P's elements in one power of ten (its largest element's), so that its columns read without long zeros
    exponent = math.floor(math.log10(max(abs(q.value) for q in rc.P)))
    scale = 10.0**-exponent
    correction = _table([f"P × 10^{-exponent}", "u", "v", "w"], [
        f"<tr><th>{axis}</th>" + "".join(_cell(gum_text(q.value * scale, q.expanded_uncertainty * scale), "num")
                                         for q in rc.P[3 * i:3 * i + 3]) + "</tr>" for i, axis in enumerate("xyz")] + [
        "<tr><th>O</th>" + "".join(_cell(gum_text(q.value, q.expanded_uncertainty), "num") for q in rc.O) + "</tr>"])
    ks = [q.coverage_factor for q in (*rc.P, *rc.O)]
    fixed = " (0 ± 0: zero by the frame's definition)" if any(q.std_uncertainty == 0 for q in rc.P) else ""
    return (f"<div><h3>{escape(_rate_label(rc.rate_hz))}: {escape(rc.model)} model, {escape(rc.frame)} frame</h3>"
            f'<p class="note">{escape(rc.reason)}</p>{table}'
            f'<p class="note">correction a = P (R - O): value ± U, P in {escape(rc.P[0].unit)}, O in {escape(rc.O[0].unit)}, '
            f"k {_span(ks)}{fixed}</p>{correction}</div>")


def results(cal: Calibration) -> str:
    return ("<h2>3. Results</h2>"
            f'<p class="note">{len(cal.rates)} rate{"s" if len(cal.rates) > 1 else ""}; per rate the recommended model, value and expanded '
            f"uncertainty U at {EXPANDED_COVERAGE:.0%} coverage.</p>"
            f'<div class="rates">{"".join(_rate_results(rc) for rc in cal.rates)}</div>')


def _image(png: bytes | None, alt: str) -> str:
    from rotcal.report.certificate_figures import data_uri  # matplotlib only when a figure is embedded

    return "" if png is None else f'<p><img alt="{escape(alt)}" src="{data_uri(png)}"></p>'


def frequency_response(run_dir: Path, tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> str:
    head = "<h2>4. Frequency response</h2>"
    response = tables.get("frequency_response")
    if response is None or response.filter(pl.col("rate_hz").is_not_null()).is_empty():
        return head + "<p>Not applicable: the run has no rotation rates referenced to the table angle.</p>"
    if not figures:
        return head + "<p>Figures were not drawn in this run (<code>[report] figures</code>): see frequency_response.parquet.</p>"
    from rotcal.report.certificate_figures import frequency_response_figure

    return head + ('<p class="note">Each parameter at each rotation rate against its static (DC) value; error bars '
                   "the standard uncertainty (Gaitan &amp; Geist 2021 Figs. 6 and 7).</p>"
                   + _image(frequency_response_figure(run_dir, response, cal.dataset), "frequency response"))


def norm_section(tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> str:
    head = "<h2>5. |a| check</h2>"
    check = norm_check(tables, cal)
    if check.is_empty():
        return head + "<p>No pose, dwell or segment fit in the run's tables to check.</p>"
    summary = _table(["from", "n", "mean (ppm)", "RMS (ppm)", "largest |dev.| (ppm)"], [
        f"<tr>{_cell(k)}{_cell(n, 'num')}{_cell(f'{m:+.1f}', 'num')}{_cell(f'{r:.1f}', 'num')}{_cell(f'{x:.1f}', 'num')}</tr>"
        for k, n, m, r, x in norm_summary(check).iter_rows()])
    rows = []
    for kind, item, _, norm, u, dev, held in check.iter_rows():
        shown = gum_text(norm, u) if u is not None else f"{norm:.6f}"
        rows.append(f"<tr>{_cell(kind)}{_cell(item)}{_cell(shown, 'num')}{_cell(f'{dev:+.1f}', 'num')}"
                    f"{_cell('' if held is None else f'{held:+.1f}', 'num')}</tr>")
    every = _table(["from", "item", "|a| (m/s², ± u)", "|a|/g - 1 (ppm)", "held out (ppm)"], rows)
    figure = ""
    if figures:
        from rotcal.report.certificate_figures import norm_figure

        figure = _image(norm_figure(check, cal.g_local), "|a| check")
    return (head + f"<p>The magnitude of the corrected acceleration against g_local = {cal.g_local:g} m/s² "
            "(poses: poses.parquet, with the two-fold held-out check and its uncertainty from the result's "
            "covariance and the pose's noise; dwells: dwells.parquet, u from the dwell's noise; segment fits: "
            "fits.parquet under their rate's calibration, averaged over a turn, u from the fit's noise).</p>"
            f"{summary}{_remark(check, cal, tables)}{figure}"
            f"<details><summary>every pose, dwell and segment ({check.height})</summary>{every}</details>")


def _remark(check: pl.DataFrame, cal: Calibration, tables: dict[str, pl.DataFrame]) -> str:
    findings = tables.get("diagnosis")
    detected = () if findings is None else tuple(dict.fromkeys(findings.filter(pl.col("detected"))["effect"].to_list()))
    remark = norm_remark(check, cal, detected)
    return f'<p class="note">{escape(remark)}</p>' if remark else ""


def diagnosis(run_dir: Path, tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> str:
    head = "<h2>6. Diagnosis</h2>"
    findings = tables.get("diagnosis")
    recommended = _table(["rate", "recommended model", "why"], [
        f"<tr>{_cell(_rate_label(r.rate_hz))}{_cell(r.model)}{_cell(r.reason)}</tr>" for r in cal.rates])
    if findings is None:
        return head + ("<p>This run was not diagnosed (the diagnosis models table segments that have the table "
                       f"angle).</p>{recommended}")
    found = findings.filter(pl.col("detected"))
    sentence = ("No finding: the recording agrees with the papers' model within its noise." if found.is_empty() else
                f"{found.height} finding{'s' if found.height > 1 else ''}: " + "; ".join(f"{e} ({w})" for e, w in found.select("effect", "where").iter_rows()))
    rows = [f"<tr>{_cell(e)}{_cell('yes' if d else 'no')}{_cell(w)}{_cell(f'{b:.6g} → {a:.6g}', 'num')}"
            f"{_cell(f'{bic:+.0f}', 'num')}{_cell(ev)}</tr>"
            for e, d, w, ev, b, a, bic in findings.select("effect", "detected", "where", "evidence", "rms_before",
                                                          "rms_after", "delta_bic").iter_rows()]
    table = _table(["effect", "detected", "where", f"residual RMS before → after ({cal.output_unit})", "ΔBIC",
                    "evidence"], rows)
    drawn = _diagnosis_figures(run_dir) if figures else []
    images = "".join(_image(p.read_bytes(), p.stem) for p in drawn)
    return head + f"<p>{escape(sentence)}</p>{recommended}{table}{images}"


def budget(tables: dict[str, pl.DataFrame], cal: Calibration) -> str:
    contributions = main_contributions(tables.get("uncertainty_budget"), cal)
    quantity = {(rc.rate_hz, q.name): q for rc in cal.rates for q in rc.parameters}
    rows = []
    for rate, name, inputs, fractions, g_share, source in contributions.iter_rows():
        q = quantity[(rate, name)]
        main = "; ".join(f"{i}: {f:.1%}" for i, f in zip(inputs, fractions))
        rows.append(f"<tr>{_cell(_rate_label(rate))}{_cell(name)}{_cell(gum_round(q.std_uncertainty, q.std_uncertainty)[1], 'num')}"
                    f"{_cell(q.unit)}{_cell(main)}{_cell(f'{g_share:.1%}', 'num')}{_cell(source)}</tr>")
    return ("<h2>7. Main contributions to the uncertainty</h2>"
            '<p class="note">The largest input groups of each standard uncertainty u (GUM 5.1.3), as fractions of '
            "the variance: from uncertainty_budget.parquet where the recommended model is the baseline it was "
            "drawn up for, else from calibration.json (g_local against the rest).</p>"
            + _table(["rate", "parameter", "u", "unit", "largest contributions", "g_local", "from"], rows))


def traceability(cal: Calibration, run_dir: Path, read: list[Path]) -> str:
    files_read = _table(["file", "SHA-256"], [f"<tr>{_cell(p.relative_to(run_dir).as_posix())}{_cell(_sha256(p), 'hash')}</tr>"
                                              for p in read])
    config = escape(json.dumps(cal.configuration, indent=1, sort_keys=True))
    return ("<h2>8. Traceability</h2>"
            + _fields([("g_local", f"{cal.g_local:g} m/s², standard uncertainty {cal.g_local_uncertainty:g} m/s²"),
                       ("g_local source", cal.g_local_source), ("rotcal version", cal.rotcal_version),
                       ("time of the run (UTC)", cal.created_utc)])
            + f"<h3>Files this page was rendered from</h3>{files_read}"
            + f"<details><summary>configuration of the run</summary><pre>{config}</pre></details>")


def _embedded(run_dir: Path) -> list[Path]:
    """The run's own figures the page embeds."""
    return [p for p in (run_dir / "frequency_response.png", *_diagnosis_figures(run_dir)) if p.is_file()]


def _diagnosis_figures(run_dir: Path) -> list[Path]:
    """report.md's figures: residuals before and after each finding, offsets against w^2."""
    return sorted((run_dir / "figures").glob("*.png"))


def _sha256(path: Path) -> str:
    with path.open("rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


@cache
def _page() -> Template:
    """The page's template (``certificate.html``), read once a process."""
    return Template(files("rotcal.report").joinpath(CERTIFICATE).read_text(encoding="utf-8"))


def render(run_dir: Path, figures: bool = True, calibration: Calibration | None = None,
           published: Mapping[str, pa.Table] | None = None) -> str:
    """The certificate page of the run in ``run_dir``; raises ``InputError``
    when it holds no readable ``calibration.json`` or an unreadable table.
    ``calibration``: the document the run itself has just written there
    (and validated), taken instead of reading it back. ``published``: the
    tables that run wrote into ``run_dir``, as it wrote them (by name),
    taken instead of reading the files back."""
    run_dir = Path(run_dir)
    cal = Calibration.read(run_dir / "calibration.json") if calibration is None else calibration
    tables = read_tables(run_dir) if published is None else {
        name: pl.DataFrame(published[name]) for name in TABLES if name in published}
    kind = run_kind(tables)
    sections = [identification(cal, kind), method(cal, kind), results(cal),
                frequency_response(run_dir, tables, cal, figures), norm_section(tables, cal, figures),
                diagnosis(run_dir, tables, cal, figures), budget(tables, cal),
                traceability(cal, run_dir, [run_dir / "calibration.json", *(run_dir / f"{n}.parquet" for n in tables),
                                   *(_embedded(run_dir) if figures else [])])]
    return _page().substitute(dataset=escape(cal.dataset), kind=escape(KINDS[kind]), version=escape(cal.rotcal_version),
                           created=escape(cal.created_utc), sections="\n".join(sections))


def write_certificate(run_dir: Path, figures: bool = True, calibration: Calibration | None = None,
                      published: Mapping[str, pa.Table] | None = None) -> Path:
    """Write ``certificate.html`` into ``run_dir`` (atomically) from its
    published files (``calibration``, ``published``: as ``render``)."""
    path = Path(run_dir) / CERTIFICATE
    text = render(Path(run_dir), figures, calibration, published)
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))
