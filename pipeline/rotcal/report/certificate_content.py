"""What the certificate says, drawn from a run's published files
(``calibration.json``, read with ``Calibration.read``, and the Parquet
tables beside it, each optional but the document) as the blocks of
``certificate_blocks``. Its main part carries what ISO/IEC 17025:2017
7.8.2.1 and 7.8.4.1 ask of a calibration certificate (the fields the
laboratory gave, ``model.identification``; absent ones "not given"); the
annex the evidence. Values with their expanded uncertainties are rounded
as GUM 7.2.6 asks (``rounding.gum_round``)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import polars as pl

from rotcal.errors import InputError
from rotcal.model.calibration import Calibration, Quantity, RateCalibration
from rotcal.model.identification import NOT_GIVEN
from rotcal.model.results import EXPANDED_COVERAGE
from rotcal.report.certificate_blocks import Approval, Block, Document, Fields, Figure, Grid, Heading, Preformatted, Section, Text
from rotcal.report.certificate_checks import main_contributions, norm_check, norm_remark, norm_summary
from rotcal.report.rounding import gum_round, gum_text
from rotcal.tables import schema

# the published tables the certificate reads, each where the run wrote it
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
BUDGET_SOURCES = {"uncertainty_budget.parquet": "uncertainty budget", "calibration.json": "covariance, g_local apart"}


def rate_label(rate_hz: float) -> str:
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


def _g_local_source(cal: Calibration) -> str:
    """Where g_local comes from, in the customer's words (no file name)."""
    return "standard gravity (no local value given)" if cal.g_local_source.startswith("standard gravity") else \
        "the laboratory's local value"


# -- the main part --------------------------------------------------------------------

def certificate_section(cal: Calibration) -> Section:
    ident = cal.identification
    return Section("1. Certificate", (
        Fields((("certificate number", ident.value("certificate", "number")),
                ("date of issue", ident.value("certificate", "date_of_issue")))),
        Heading("Calibration laboratory"), Fields(tuple(ident.shown("laboratory"))),
        Heading("Customer"), Fields(tuple(ident.shown("customer")))))


def item_section(cal: Calibration) -> Section:
    ident = cal.identification
    return Section("2. Item calibrated", (
        Fields((("kind", "three-axis accelerometer"), *ident.shown("item"), ("output unit", cal.output_unit))),))


def measurement_section(cal: Calibration, kind: str) -> Section:
    ident = cal.identification
    return Section("3. Measurement", (Fields((
        ("date of measurement", ident.value("certificate", "date_of_measurement")),
        ("place of calibration", ident.value("certificate", "place")),
        ("temperature", ident.value("certificate", "temperature")),
        ("relative humidity", ident.value("certificate", "humidity")),
        *((("other conditions", ident.value("certificate", "conditions")),) if ident.certificate.conditions else ()),
        ("kind of measurement", KINDS[kind]))),))


def method_section(cal: Calibration, kind: str) -> Section:
    frames = sorted({r.frame for r in cal.rates})
    where = f"the {frames[0]} frame" if len(frames) == 1 else "the frame each rate's results name"
    return Section("4. Method and conventions", (
        Text(f"Method: {METHODS[kind]}"),
        Text("Conventions: u, v, w are the item's output channels and x, y, z the axes of the frame of P's rows "
             f"({where}); s is each channel's sensitivity, phi the angles between the sensitive axes, O the offsets; "
             "the calibrated acceleration is a = P (R - O) for a raw output R. Each expanded uncertainty U = k u "
             "with k = t(0.975; ν_eff) for a coverage probability of 95 % (GUM G.4), rounded to two significant "
             "digits, the value to the same decimal place (GUM 7.2.6)."),))


def equipment_section(cal: Calibration) -> Section:
    ident = cal.identification
    return Section("5. Equipment and traceability", (
        Fields((*ident.shown("equipment")[:-1],
                ("g_local", f"{cal.g_local:g} m/s², standard uncertainty {cal.g_local_uncertainty:g} m/s²"),
                ("g_local source", _g_local_source(cal)),
                ident.shown("equipment")[-1],
                ("software", f"rotcal {cal.rotcal_version}"))),))


def _rate_results(rc: RateCalibration) -> list[Block]:
    rows = [(q.name, *gum_round(q.value, q.expanded_uncertainty), f"{q.coverage_factor:.2f}", _dof(q), q.unit)
            for q in rc.parameters]
    results = Grid(("parameter", "value", "U (95 %)", "k", "ν_eff", "unit"), tuple(rows),
                   ("", "num value", "num U", "num k", "num dof", ""),
                   tuple((("rate", repr(rc.rate_hz)), ("parameter", q.name)) for q in rc.parameters))
    # P's elements in one power of ten (its largest element's), so that its columns read without long zeros
    exponent = math.floor(math.log10(max(abs(q.value) for q in rc.P)))
    scale = 10.0**-exponent
    correction = Grid((f"P × 10^{-exponent}", "u", "v", "w"), tuple(
        (axis, *(gum_text(q.value * scale, q.expanded_uncertainty * scale) for q in rc.P[3 * i:3 * i + 3]))
        for i, axis in enumerate("xyz")) + (("O", *(gum_text(q.value, q.expanded_uncertainty) for q in rc.O)),),
        ("", "num", "num", "num"), row_heads=True)
    ks = [q.coverage_factor for q in (*rc.P, *rc.O)]
    low, high = f"{min(ks):.2f}", f"{max(ks):.2f}"
    fixed = " (0 ± 0: zero by the frame's definition)" if any(q.std_uncertainty == 0 for q in rc.P) else ""
    return [Heading(f"{rate_label(rc.rate_hz)}: {rc.model} model, {rc.frame} frame"), Text(rc.reason, note=True), results,
            Text(f"correction a = P (R - O): value ± U, P in {rc.P[0].unit}, O in {rc.O[0].unit}, "
                 f"k {low if low == high else f'{low} to {high}'}{fixed}", note=True), correction]


def results_section(cal: Calibration) -> Section:
    return Section("6. Results", (
        Text(f"{len(cal.rates)} rate{'s' if len(cal.rates) > 1 else ''}; per rate the recommended model, value and "
             f"expanded uncertainty U at {EXPANDED_COVERAGE:.0%} coverage.", note=True),
        *(b for rc in cal.rates for b in _rate_results(rc))))


def budget_section(tables: dict[str, pl.DataFrame], cal: Calibration) -> Section:
    contributions = main_contributions(tables.get("uncertainty_budget"), cal)
    quantity = {(rc.rate_hz, q.name): q for rc in cal.rates for q in rc.parameters}
    rows = []
    for rate, name, inputs, fractions, g_share, source in contributions.iter_rows():
        q = quantity[(rate, name)]
        rows.append((rate_label(rate), name, gum_round(q.std_uncertainty, q.std_uncertainty)[1], q.unit,
                     "; ".join(f"{i}: {f:.1%}" for i, f in zip(inputs, fractions)), f"{g_share:.1%}",
                     BUDGET_SOURCES.get(source, source)))
    return Section("7. Main contributions to the uncertainty", (
        Text("The largest input groups of each standard uncertainty u (GUM 5.1.3), as fractions of the variance: "
             "from the uncertainty budget where the recommended model is the baseline it was drawn up for, else "
             "from the result's covariance, g_local apart from the rest.", note=True),
        Grid(("rate", "parameter", "u", "unit", "largest contributions", "g_local", "from"), tuple(rows),
             ("", "", "num", "", "", "num", ""))))


def approval(cal: Calibration) -> Approval:
    ident = cal.identification
    return Approval(ident.value("certificate", "approved_by"), ident.value("certificate", "function"),
                    ident.value("certificate", "date_of_issue"))


# -- the annex ---------------------------------------------------------------------------

def _image(png: bytes | None, alt: str) -> tuple[Block, ...]:
    return () if png is None else (Figure(png, alt),)


def frequency_response_section(run_dir: Path, tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> Section:
    title = "A.1 Frequency response"
    response = tables.get("frequency_response")
    if response is None or response.filter(pl.col("rate_hz").is_not_null()).is_empty():
        return Section(title, (Text("Not applicable: the run has no rotation rates referenced to the table angle."),))
    if not figures:
        return Section(title, (Text("Figures were not drawn in this run ([report] figures)."),))
    from rotcal.report.certificate_figures import frequency_response_figure  # matplotlib only when a figure is drawn

    return Section(title, (Text("Each parameter at each rotation rate against its static (DC) value; error bars the "
                                "standard uncertainty (Gaitan & Geist 2021 Figs. 6 and 7).", note=True),
                           *_image(frequency_response_figure(run_dir, response, cal.dataset), "frequency response")))


def norm_section(tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> Section:
    title = "A.2 |a| check"
    check = norm_check(tables, cal)
    if check.is_empty():
        return Section(title, (Text("No pose, dwell or segment fit in the run's tables to check."),))
    summary = Grid(("from", "n", "mean (ppm)", "RMS (ppm)", "largest |dev.| (ppm)"), tuple(
        (k, str(n), f"{m:+.1f}", f"{r:.1f}", f"{x:.1f}") for k, n, m, r, x in norm_summary(check).iter_rows()),
        ("", "num", "num", "num", "num"))
    rows = tuple((kind, item, gum_text(norm, u) if u is not None else f"{norm:.6f}", f"{dev:+.1f}",
                  "" if held is None else f"{held:+.1f}") for kind, item, _, norm, u, dev, held in check.iter_rows())
    every = Grid(("from", "item", "|a| (m/s², ± u)", "|a|/g - 1 (ppm)", "held out (ppm)"), rows,
                 ("", "", "num", "num", "num"), folded=f"every pose, dwell and segment ({check.height})")
    figure: tuple[Block, ...] = ()
    if figures:
        from rotcal.report.certificate_figures import norm_figure

        figure = _image(norm_figure(check, cal.g_local), "|a| check")
    return Section(title, (
        Text(f"The magnitude of the corrected acceleration against g_local = {cal.g_local:g} m/s² (poses: with the "
             "two-fold held-out check and its uncertainty from the result's covariance and the pose's noise; dwells: "
             "u from the dwell's noise; segment fits: under their rate's calibration, averaged over a turn, u from "
             "the fit's noise)."), summary, *_remark(check, cal, tables), *figure, every))


def _remark(check: pl.DataFrame, cal: Calibration, tables: dict[str, pl.DataFrame]) -> tuple[Block, ...]:
    """Why items lie beyond their uncertainty, where the check says (``norm_remark``)."""
    findings = tables.get("diagnosis")
    detected = () if findings is None else tuple(dict.fromkeys(findings.filter(pl.col("detected"))["effect"].to_list()))
    remark = norm_remark(check, cal, detected)
    return (Text(remark, note=True),) if remark else ()


def diagnosis_section(run_dir: Path, tables: dict[str, pl.DataFrame], cal: Calibration, figures: bool) -> Section:
    title = "A.3 Diagnosis"
    findings = tables.get("diagnosis")
    recommended = Grid(("rate", "recommended model", "why"), tuple((rate_label(r.rate_hz), r.model, r.reason) for r in cal.rates))
    if findings is None:
        return Section(title, (Text("This run was not diagnosed (the diagnosis models table segments that have the "
                                    "table angle)."), recommended))
    found = findings.filter(pl.col("detected"))
    sentence = ("No finding: the recording agrees with the papers' model within its noise." if found.is_empty() else
                f"{found.height} finding{'s' if found.height > 1 else ''}: "
                + "; ".join(f"{e} ({w})" for e, w in found.select("effect", "where").iter_rows()))
    rows = tuple((e, "yes" if d else "no", w, f"{b:.6g} → {a:.6g}", f"{bic:+.0f}", ev)
                 for e, d, w, ev, b, a, bic in findings.select("effect", "detected", "where", "evidence", "rms_before",
                                                               "rms_after", "delta_bic").iter_rows())
    table = Grid(("effect", "detected", "where", f"residual RMS before → after ({cal.output_unit})", "ΔBIC", "evidence"),
                 rows, ("", "", "", "num", "num", ""))
    drawn = diagnosis_figures(run_dir) if figures else []
    return Section(title, (Text(sentence), recommended, table, *(Figure(p.read_bytes(), p.stem) for p in drawn)))


def records_section(cal: Calibration, run_dir: Path, read: list[Path], kind: str) -> Section:
    ident = cal.identification
    inputs = Grid(("input file", "bytes", "SHA-256"), tuple((f["path"], str(f["bytes"]), f["sha256"]) for f in cal.inputs),
                  ("", "num", "hash"))
    files_read = Grid(("file", "SHA-256"), tuple((p.relative_to(run_dir).as_posix(), sha256(p)) for p in read), ("", "hash"))
    device = [(f"device {k}", "" if v is None else str(v)) for k, v in cal.device.items() if k != "output_unit"]
    site = ident.site_file
    return Section("A.4 Records", (
        Fields((("dataset", cal.dataset), *device, ("kind of run", KINDS[kind]), ("rotcal version", cal.rotcal_version),
                ("time of the run (UTC)", cal.created_utc), ("g_local as given", cal.g_local_source),
                ("site file", NOT_GIVEN if site is None else f"{site.path} (SHA-256 {site.sha256})"))),
        Heading("Inputs (content hashes)"), inputs,
        Heading("Files this certificate was rendered from"), files_read,
        Preformatted(json.dumps(cal.configuration, indent=1, sort_keys=True), folded="configuration of the run")))


def diagnosis_figures(run_dir: Path) -> list[Path]:
    """report.md's figures: residuals before and after each finding, offsets against w^2."""
    return sorted((run_dir / "figures").glob("*.png"))


def embedded(run_dir: Path) -> list[Path]:
    """The run's own figures the certificate embeds."""
    return [p for p in (run_dir / "frequency_response.png", *diagnosis_figures(run_dir)) if p.is_file()]


def sha256(path: Path) -> str:
    with path.open("rb") as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def certificate_document(run_dir: Path, cal: Calibration, tables: dict[str, pl.DataFrame], figures: bool) -> Document:
    """The certificate of the run in ``run_dir`` whose document is ``cal`` and whose tables are ``tables``."""
    kind = run_kind(tables)
    read = [run_dir / "calibration.json", *(run_dir / f"{n}.parquet" for n in tables), *(embedded(run_dir) if figures else [])]
    ident = cal.identification
    return Document(
        "Calibration certificate", f"three-axis accelerometer · {KINDS[kind]}",
        ident.value("laboratory", "name"), ident.value("certificate", "number"),
        (certificate_section(cal), item_section(cal), measurement_section(cal, kind), method_section(cal, kind),
         equipment_section(cal), results_section(cal), budget_section(tables, cal)),
        approval(cal),
        (frequency_response_section(run_dir, tables, cal, figures), norm_section(tables, cal, figures),
         diagnosis_section(run_dir, tables, cal, figures), records_section(cal, run_dir, read, kind)),
        generated=f"rendered by rotcal {cal.rotcal_version}, {cal.created_utc}", created_utc=cal.created_utc)
