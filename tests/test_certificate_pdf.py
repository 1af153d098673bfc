"""The certificate's ISO/IEC 17025:2017 content (7.8.2.1, 7.8.4.1) and its
PDF: a run whose dataset.toml and site file give every field shows each
in the PDF's text (read back with pypdf), on every page the laboratory,
the certificate number and "page x of y"; a run that gives none shows
each as "not given"; the customer-facing part names no file of the run;
the annex prints whole what the HTML folds away; bad fields are one-line
errors (exit 2)."""

from __future__ import annotations

import re
import shutil
from dataclasses import replace
from pathlib import Path

import pypdf
import pytest

from rotcal.batch.plan import batch_site, config_json
from rotcal.config import RunConfig
from rotcal.errors import InputError
from rotcal.ingest.meta import load_meta
from rotcal.ingest.site import load_site
from rotcal.model.calibration import Calibration
from rotcal.model.identification import NOT_GIVEN
from rotcal.report.certificate import CERTIFICATE, CERTIFICATE_PDF, rewrite_certificates
from rotcal.run import run_dataset
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

DATASET_PARTS = """
[customer]
name = "Aerodyne Flight Systems GmbH"
address = "Hangarstrasse 4, 85521 Ottobrunn"
reference = "PO 4711-2026"

[item]
make = "Bosch Sensortec"
model = "BMI088"
serial_number = "SN-0042-7781"
range = "±6 g"
output_rate = "1600 Hz"
filter = "digital low-pass, normal mode"

[certificate]
number = "K-2026-0815"
date_of_measurement = [2026-03-02, 2026-03-03]
date_of_issue = 2026-03-05
temperature = "(23.0 ± 0.5) °C"
humidity = "(45 ± 10) %"
"""
SITE = """
[laboratory]
name = "Inertial Metrology Laboratory"
address = "Messweg 1, 38116 Braunschweig"

[equipment]
rotation_table = "Acutronic AC1120S, serial 1234"
angle_reference = "table encoder, 2^23 counts per turn"
angle_traceability = "angle certificate 2025-117"
rate_reference = "encoder and oscillator"
rate_traceability = "through the angle and clock references"
clock_reference = "GPS-disciplined 10 MHz oscillator"
clock_traceability = "UTC via GNSS, certificate 2025-033"
g_local_traceability = "absolute gravimeter survey, report G-19-07"

[certificate]
place = "permanent laboratory, room 1.23"
approved_by = "Dr. Jane Example"
function = "head of laboratory"
"""
# every 17025 item the fields above give, as the certificate shows it: (label, value)
GIVEN = [("laboratory", "Inertial Metrology Laboratory"), ("address", "Messweg 1, 38116 Braunschweig"),
         ("customer", "Aerodyne Flight Systems GmbH"), ("address", "Hangarstrasse 4, 85521 Ottobrunn"),
         ("make", "Bosch Sensortec"), ("model", "BMI088"), ("serial number", "SN-0042-7781"), ("range", "±6 g"),
         ("output rate", "1600 Hz"), ("filter", "digital low-pass, normal mode"),
         ("certificate number", "K-2026-0815"), ("date of issue", "2026-03-05"),
         ("date of measurement", "2026-03-02 to 2026-03-03"), ("place of calibration", "permanent laboratory, room 1.23"),
         ("temperature", "(23.0 ± 0.5) °C"), ("relative humidity", "(45 ± 10) %"),
         ("rotation table", "Acutronic AC1120S, serial 1234"), ("angle reference", "table encoder, 2^23 counts per turn"),
         ("angle traceability", "angle certificate 2025-117"), ("rate reference", "encoder and oscillator"),
         ("rate traceability", "through the angle and clock references"),
         ("clock reference", "GPS-disciplined 10 MHz oscillator"), ("clock traceability", "UTC via GNSS, certificate 2025-033"),
         ("g_local traceability", "absolute gravimeter survey, report G-19-07"),
         ("approved by", "Dr. Jane Example"), ("function", "head of laboratory")]
STATEMENTS = ["The results relate only to the item calibrated.",
              "This certificate shall not be reproduced except in full without the written approval of the issuing laboratory."]


def _text(pdf: Path) -> list[str]:
    """Each page's text, whitespace collapsed to single spaces."""
    return [" ".join(page.extract_text().split()) for page in pypdf.PdfReader(pdf).pages]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same simulated dataset run twice: with every field (dataset.toml and the site file beside
    it, found by itself) and with none (no site file, no certificate parts)."""
    root = tmp_path_factory.mktemp("cert17025")
    spec = SimulationSpec(plan=Plan(rates_hz=(0.1,), rotation_samples=1000))
    given = write_dataset(simulate(spec, 5), spec, root / "lab" / "DUT-7", "csv")
    with (given / "dataset.toml").open("a", encoding="utf-8") as fh:
        fh.write(DATASET_PARTS)
    (root / "lab" / "site.toml").write_text(SITE, encoding="utf-8")
    bare = write_dataset(simulate(spec, 5), spec, root / "bare" / "DUT-7", "csv")
    out = {"given": root / "given_out", "bare": root / "bare_out"}
    run_dataset(given, out["given"])
    run_dataset(bare, out["bare"])
    return out


def test_every_17025_item_is_in_the_pdf(runs):
    pages = _text(runs["given"] / CERTIFICATE_PDF)
    whole = " ".join(pages)
    for label, value in GIVEN:
        assert f"{label} {value}" in whole, (label, value)
    for statement in STATEMENTS:
        assert statement in whole
    assert "signature" in whole and NOT_GIVEN not in whole
    # every page: the laboratory, the certificate number, page x of y
    for k, page in enumerate(pages, 1):
        assert "Inertial Metrology Laboratory" in page and "K-2026-0815" in page
        assert f"page {k} of {len(pages)}" in page
    assert len(pages) >= 3 and "End of certificate K-2026-0815" in pages[-1]  # and where it ends (7.8.2.1 e)
    # the site file the run read, with its content's hash, in the records
    cal = Calibration.read(runs["given"])
    assert cal.identification.site_file is not None and cal.identification.site_file.sha256 in whole


def test_without_the_fields_each_is_shown_as_not_given(runs):
    whole = " ".join(_text(runs["bare"] / CERTIFICATE_PDF))
    for label, _ in GIVEN:
        assert f"{label} {NOT_GIVEN}" in whole, label
    assert "page 1 of" in whole and "laboratory not given" in whole and "number not given" in whole
    html = (runs["bare"] / CERTIFICATE).read_text(encoding="utf-8")
    # and the date of issue again beside the signature, the site file in the records
    assert html.count('<td class="absent">not given</td>') == len(GIVEN) + 2


@pytest.mark.parametrize("kind", ["given", "bare"])
def test_the_customer_facing_part_names_no_file(runs, kind):
    """Files of the run (tables, documents, configuration) are named only in the annex."""
    whole = " ".join(_text(runs[kind] / CERTIFICATE_PDF))
    main, annex = whole.split("Annex: evidence and records")
    assert not re.search(r"\.(parquet|json|toml|md|csv|png)\b|docs/", main), re.findall(r"\S+\.(?:parquet|json|toml|md)", main)
    assert "calibration.json" in annex
    html = (runs[kind] / CERTIFICATE).read_text(encoding="utf-8")
    assert not re.search(r"\.(parquet|json|toml|md)\b|docs/", html.split('class="annex"')[0].split("<body>")[1])


def test_the_annex_prints_what_the_html_folds_away(runs):
    html = (runs["given"] / CERTIFICATE).read_text(encoding="utf-8")
    folded = re.findall(r"<details><summary>([^<]*)</summary>", html)
    assert "configuration of the run" in folded and any(f.startswith("every pose, dwell and segment") for f in folded)
    whole = " ".join(_text(runs["given"] / CERTIFICATE_PDF))
    for summary in folded:
        assert summary in whole
    # every row of the folded |a| table and the configuration's keys
    rows = re.findall(r"<td>(segment \d+ \([^<]*\))</td>", html)
    assert rows and all(row in whole for row in rows)
    assert '"sine_fit": "three_parameter"' in whole


def test_a4_by_default_letter_by_option_and_the_same_bytes_again(runs, tmp_path):
    reader = pypdf.PdfReader(runs["given"] / CERTIFICATE_PDF)
    size = reader.pages[0].mediabox
    assert (round(float(size.width)), round(float(size.height))) == (595, 842)  # A4, 210 x 297 mm in points
    # declared PDF/A-2b, dated the time of the run
    xmp = reader.trailer["/Root"]["/Metadata"].get_data().decode()
    assert "<pdfaid:part>2</pdfaid:part><pdfaid:conformance>B</pdfaid:conformance>" in xmp
    assert f"<xmp:CreateDate>{Calibration.read(runs['given']).created_utc}</xmp:CreateDate>" in xmp
    run = tmp_path / "letter"
    shutil.copytree(runs["given"], run)
    before = (run / CERTIFICATE_PDF).read_bytes()
    assert rewrite_certificates(run) == [run / CERTIFICATE, run / CERTIFICATE_PDF]
    assert (run / CERTIFICATE_PDF).read_bytes() == before  # drawn again from the files: the same bytes
    cal = Calibration.read(run)
    config = dict(cal.configuration, report={**cal.configuration["report"], "paper": "letter"})
    cal.__class__(**{**cal.__dict__, "configuration": config}).write(run / "calibration.json")
    rewrite_certificates(run)
    size = pypdf.PdfReader(run / CERTIFICATE_PDF).pages[0].mediabox
    assert (round(float(size.width)), round(float(size.height))) == (612, 792)  # US Letter, 8.5 x 11 in


def test_no_pdf_when_switched_off(tmp_path, runs):
    spec = SimulationSpec(plan=Plan(rates_hz=(0.1,), rotation_samples=1000))
    data = write_dataset(simulate(spec, 5), spec, tmp_path / "d", "csv")
    config = replace(RunConfig(), report=replace(RunConfig().report, pdf=False, figures=False))
    written = run_dataset(data, tmp_path / "out", config=config).written
    assert CERTIFICATE_PDF not in [p.name for p in written] and not (tmp_path / "out" / CERTIFICATE_PDF).exists()
    assert rewrite_certificates(tmp_path / "out") == [tmp_path / "out" / CERTIFICATE]


@pytest.mark.parametrize(("text", "message"), [
    ('[item]\nserial = "1"\n', "unknown key 'serial' in [item]"),
    ("[certificate]\nnumber = 42\n", "certificate.number: 42 is not of type 'string'"),
    ('[customer]\nname = ""\n', "customer.name"),
    ("[certificate]\ndate_of_issue = 2026-03-01\ndate_of_measurement = 2026-03-02\n",
     "certificate.date_of_issue 2026-03-01 is before the measurement ended (2026-03-02)"),
    ("[certificate]\ndate_of_measurement = [2026-03-04, 2026-03-02]\n",
     "certificate.date_of_measurement runs from 2026-03-04 back to 2026-03-02"),
    ('[certificate]\ndate_of_issue = "2026-02-30"\n', "certificate.date_of_issue = '2026-02-30' is not a calendar date"),
])
def test_bad_fields_in_dataset_toml(tmp_path, text, message):
    path = tmp_path / "dataset.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        load_meta(path)
    assert str(path) in str(caught.value) and "\n" not in str(caught.value)


@pytest.mark.parametrize(("text", "message"), [
    ('[certificate]\nnumber = "K-1"\n', "certificate.number is one certificate's: give it in dataset.toml"),
    ('[customer]\nname = "x"\n', "[customer] belongs in dataset.toml"),
    ('[laboratory]\nname = "x"\nphone = "1"\n', "unknown key 'phone' in [laboratory]"),
    ("[equipment\n", "site file is not valid TOML"),
])
def test_bad_site_files(tmp_path, text, message):
    path = tmp_path / "site.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(InputError, match=re.escape(message)):
        load_site(path)


def test_bad_site_file_on_the_command_line(tmp_path, runs, cli):
    site = tmp_path / "site.toml"
    site.write_text('[laboratory]\nname = 3\n', encoding="utf-8")
    source = runs["bare"].parent / "bare" / "DUT-7"
    code, _, err = cli("run", source, "--out", tmp_path / "out", "--site", site)
    assert code == 2 and "site.toml" in err and "laboratory.name" in err and len(err.strip().splitlines()) == 1, err
    code, _, err = cli("run", source, "--out", tmp_path / "out", "--site", tmp_path / "none.toml")
    assert code == 2 and "site file not found" in err, err


def test_the_dataset_overrides_the_site_field_by_field(tmp_path):
    (tmp_path / "site.toml").write_text(SITE, encoding="utf-8")
    (tmp_path / "dataset.toml").write_text('[certificate]\nplace = "customer\'s site, hangar 2"\n', encoding="utf-8")
    merged = load_meta(tmp_path / "dataset.toml").identification.over(load_site(tmp_path / "site.toml"))
    assert merged.certificate.place == "customer's site, hangar 2"
    assert merged.certificate.approved_by == "Dr. Jane Example" and merged.laboratory.name == "Inertial Metrology Laboratory"


def test_a_batch_reads_roots_site_file_and_reruns_when_it_changes(tmp_path):
    assert batch_site(tmp_path, RunConfig()) == RunConfig()  # none: no error, the fields not given
    (tmp_path / "site.toml").write_text(SITE, encoding="utf-8")
    config = batch_site(tmp_path, RunConfig())
    assert config.report.site == str((tmp_path / "site.toml").resolve())
    before = config_json(config)
    (tmp_path / "site.toml").write_text(SITE.replace("room 1.23", "room 1.24"), encoding="utf-8")
    assert config_json(config) != before
    (tmp_path / "site.toml").write_text('[certificate]\nnumber = "K-1"\n', encoding="utf-8")
    with pytest.raises(InputError, match="one certificate's"):
        batch_site(tmp_path, RunConfig())


def test_the_schema_and_the_record_name_the_same_fields():
    """dataset.toml's contract (schemas/dataset_toml.json) and model.identification: one set of keys per part."""
    import dataclasses

    from rotcal.model.identification import LABELS, PARTS
    from rotcal_schemas import schema_text

    properties = schema_text("dataset_toml")["properties"]
    for part, kind in PARTS.items():
        fields = [f.name for f in dataclasses.fields(kind)]
        assert list(properties[part]["properties"]) == fields == list(LABELS[part]), part


def test_a_calibration_document_without_certificate_fields_still_reads(runs, tmp_path):
    """Version 1.0 documents have no ``certificate``; a later 1.x may add fields this reader leaves out."""
    import json

    doc = json.loads((runs["given"] / "calibration.json").read_text(encoding="utf-8"))
    assert doc["version"] == "1.1" and doc["certificate"]["item"]["serial_number"] == "SN-0042-7781"
    doc["certificate"]["item"]["colour"] = "blue"
    assert Calibration.from_dict(doc).identification.item.serial_number == "SN-0042-7781"
    doc.pop("certificate")
    doc["version"] = "1.0"
    (tmp_path / "calibration.json").write_text(json.dumps(doc), encoding="utf-8")
    assert Calibration.read(tmp_path).identification.item.serial_number is None


def test_a_batch_notes_a_certificate_number_two_datasets_give(tmp_path):
    from rotcal.batch.plan import Found, Plan, shared_certificate_numbers

    plans = []
    for name, number in (("a", "K-1"), ("b", "K-2"), ("c", "K-1"), ("d", None)):
        (tmp_path / name).mkdir()
        (tmp_path / name / "dataset.toml").write_text("" if number is None else f'[certificate]\nnumber = "{number}"\n')
        plans.append(Plan(Found(name, tmp_path / name), name, "", "[]", None, {}))
    assert shared_certificate_numbers(plans) == (
        "certificate number 'K-1' is given by 2 datasets (a, c): each certificate needs its own",)
    assert shared_certificate_numbers(plans[:2] + [replace(plans[2], refusal="bad")]) == ()
