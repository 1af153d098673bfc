"""The calibration certificate (rotcal.report.certificate): GUM 7.2.6
rounding by hand, the |a| check and the budget summary against
hand-derived values, and the page of a table run, a static-pose run and an
unlabelled run parsed back: every parameter of every rate with its value,
U and k as calibration.json has them, and no resource outside the page."""

from __future__ import annotations

import math
import shutil
from dataclasses import replace
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from rotcal.config import RunConfig
from rotcal.errors import InputError
from rotcal.model.calibration import Calibration, Quantity, RateCalibration
from rotcal.model.outputs import OUTPUTS
from rotcal.model.physics import CHANNELS, INTRINSIC
from rotcal.report.certificate import CERTIFICATE, render, write_certificate
from rotcal.report.certificate_checks import main_contributions, segment_norms
from rotcal.report.rounding import decimals_for, gum_round, gum_text
from rotcal.run import run_dataset
from rotcal.run.outputs import certificate_outputs
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

from posesim import hand_placed, samples_frame

SECTIONS = ["1. Certificate", "2. Item calibrated", "3. Measurement", "4. Method and conventions",
            "5. Equipment and traceability", "6. Results", "7. Main contributions to the uncertainty", "8. Approval",
            "Annex: evidence and records", "A.1 Frequency response", "A.2 |a| check", "A.3 Diagnosis", "A.4 Records"]


@pytest.mark.parametrize(("value", "u", "expected"), [
    (1671.41234, 0.0491, ("1671.412", "0.049")),  # report.md printed "1671.4 ± 0.049"
    (1671.4, 0.049, ("1671.400", "0.049")),
    (0.123456, 0.00367, ("0.1235", "0.0037")),
    (12345.6, 123.0, ("12350", "120")),  # U >= 100: the value to the tens
    (9.80665, 0.0996, ("9.81", "0.10")),  # U rounds up into a new digit: two places, not three
    (2.5, 99.7, ("0", "100")),
    (-0.0004, 0.0123, ("0.000", "0.012")),  # no "-0.000"
    (33123.834, 0.53, ("33123.83", "0.53")),
    (-418.7396, 0.26, ("-418.74", "0.26")),
    (1.0, 1.0, ("1.0", "1.0")),
    (5.0, 0.0, ("5", "0")),  # nothing to round to: six significant digits
])
def test_gum_rounding_by_hand(value, u, expected):
    assert gum_round(value, u) == expected
    assert gum_text(value, u) == f"{expected[0]} ± {expected[1]}"


def test_decimal_places_by_hand():
    assert [decimals_for(u) for u in (0.0491, 0.0996, 0.095, 123.0, 1.0, 9.96, 0.001)] == [3, 2, 3, -1, 1, 0, 4]


def _cal(P: np.ndarray, O: np.ndarray, rate: float = 0.0, g: float = 9.8, u_g: float = 0.0,  # noqa: E741
         parameters: tuple[Quantity, ...] = ()) -> Calibration:
    qs = tuple(Quantity(f"P{i}", float(v), 0.0, math.inf, "") for i, v in enumerate(P.ravel()))
    os_ = tuple(Quantity(f"O_{c}", float(v), 0.0, math.inf, "bit") for c, v in zip(CHANNELS, O))
    rc = RateCalibration(rate, "baseline", "", "table", parameters, np.zeros((9, 9)), qs, qs, os_, np.zeros((12, 12)))
    return Calibration("d", {}, "bit", g, u_g, "test", (), {}, "0", "2026-01-01T00:00:00Z", (rc,))


def _fits(coef: np.ndarray, sigma: float, rate: float = 0.1) -> pl.DataFrame:
    """One segment's three channel fits (C, A, B per channel), each coefficient with variance sigma^2, uncorrelated."""
    rows = []
    for r, c in enumerate(CHANNELS):
        covs = {f"cov_{o}": list((np.eye(3) * sigma**2 if o == c else np.zeros((3, 3))).ravel()) for o in CHANNELS}
        rows.append({"segment": 4, "kind": "rotation", "axis": "z", "rate_hz": rate, "channel": c, "status": "ok",
                     "C": coef[r, 0], "A": coef[r, 1], "B": coef[r, 2], **covs})
    return pl.DataFrame(rows)


def test_segment_norm_by_hand():
    """P = I/s, O: C = O, A along u and B along v of size s g: |a|^2 = (g^2 + g^2)/2 = g^2; only A_u and B_v
    move |a| (each by 1/(2s) per unit), so u(|a|) = sigma / (s sqrt 2)."""
    s, g, sigma = 1000.0, 9.8, 3.0
    O = np.array([10.0, -20.0, 30.0])  # noqa: E741
    coef = np.column_stack([O, [s * g, 0, 0], [0, s * g, 0]])
    check = segment_norms(_fits(coef, sigma), _cal(np.eye(3) / s, O, rate=0.1, g=g))
    assert check["norm_m_s2"][0] == pytest.approx(g, rel=1e-14)
    assert check["deviation_ppm"][0] == pytest.approx(0.0, abs=1e-6)
    assert check["u_norm_m_s2"][0] == pytest.approx(sigma / (s * math.sqrt(2)), rel=1e-12)
    # a 100 ppm larger A_u and B_v: |a| = g (1 + 1e-4)
    coef[0, 1] *= 1 + 1e-4
    coef[1, 2] *= 1 + 1e-4
    assert segment_norms(_fits(coef, sigma), _cal(np.eye(3) / s, O, rate=0.1, g=g))["deviation_ppm"][0] == pytest.approx(100.0, rel=1e-9)
    assert segment_norms(_fits(coef, sigma), _cal(np.eye(3) / s, O, rate=0.5, g=g)).is_empty()  # no calibration at 0.1 Hz


def test_budget_without_its_table_separates_g_local_by_hand():
    """s = 1000 bit/(m/s^2), u(g)/g = 1e-5: g_local gives s u(g)/g = 0.01 of u = 0.02, a quarter of the variance."""
    params = (Quantity("s_u", 1000.0, 0.02, 50.0, "bit/(m/s^2)"), Quantity("phi_uv", 90.0, 0.001, 50.0, "deg"))
    cal = _cal(np.eye(3), np.zeros(3), g=9.8, u_g=9.8e-5, parameters=params)
    got = {p: (i, f, g_share) for _, p, i, f, g_share, source in main_contributions(None, cal).iter_rows()}
    assert got["s_u"][2] == pytest.approx(0.25) and got["s_u"][1] == pytest.approx([0.75, 0.25])
    assert got["phi_uv"] == (["the rest (noise, Type A)"], [1.0], 0.0)
    # the budget table describes the baseline model: used for a baseline rate, not for a refined one
    table = pl.DataFrame({"rate_hz": 0.0, "parameter": "s_u", "source": ["noise", "g_local", "combined"],
                          "segment": [3, None, None], "axis": ["x", "", ""], "fraction": [0.9, 0.1, 1.0]})
    by_table = main_contributions(table, cal).row(0)
    assert by_table[2:] == (["noise of segment 3 (axis x)", "g_local"], [0.9, 0.1], 0.1, "uncertainty_budget.parquet")
    refined = replace(cal, rates=(replace(cal.rates[0], model="refined"),))
    assert main_contributions(table, refined).row(0)[4:] == (0.25, "calibration.json")


class _Page(HTMLParser):
    """Headings, result rows (data-rate, data-parameter, cell classes), and every attribute that loads something."""

    def __init__(self) -> None:
        super().__init__()
        self.rows: dict[tuple[float, str], dict[str, str]] = {}
        self.headings: list[str] = []
        self.loads: list[str] = []
        self.styles: list[str] = []
        self.images = 0
        self._row: tuple[float, str] | None = None
        self._cell: str | None = None
        self._tag: str | None = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self._tag = tag
        self.loads += [v or "" for k, v in attrs if k in ("src", "href", "srcset", "data", "action", "poster")]
        self.images += tag == "img"
        if tag in ("link", "script", "iframe", "object", "embed"):
            self.loads.append(f"<{tag}>")
        if tag == "tr" and "data-parameter" in a:
            self._row = (float(a["data-rate"]), a["data-parameter"])
            self.rows[self._row] = {}
        if tag == "td" and self._row is not None:
            self._cell = next((c for c in (a.get("class") or "").split() if c in ("value", "U", "k")), None)

    def handle_endtag(self, tag):
        if tag == "tr":
            self._row = None
        self._cell = None if tag == "td" else self._cell

    def handle_data(self, data):
        if self._tag == "h2":
            self.headings.append(data.strip())
        if self._tag == "style":
            self.styles.append(data)
        if self._row is not None and self._cell is not None:
            self.rows[self._row][self._cell] = data
        self._tag = None if self._tag in ("h2", "style") else self._tag


def _parsed(run: Path) -> _Page:
    page = _Page()
    page.feed((run / CERTIFICATE).read_text(encoding="utf-8"))
    return page


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A table run (two rates, diagnosed), a static-pose run (24 hand-placed poses) and an unlabelled one."""
    root = tmp_path_factory.mktemp("cert")
    table = SimulationSpec(plan=Plan(rates_hz=(0.1, 0.5), rotation_samples=1000))
    unlabelled = SimulationSpec(plan=Plan(continuous=True, rates_hz=(0.1, 0.5), rotation_samples=1000))
    static = root / "static_data"
    static.mkdir()
    samples_frame(hand_placed(77, n_poses=24, samples=300, move_samples=150)).write_csv(static / "session.csv")
    (static / "dataset.toml").write_text('[device]\nid = "dut-7"\noutput_unit = "count"\n\n[site]\ng_local = 9.80101\n'
                                         "g_local_uncertainty = 1e-4\n")
    data = {"table": write_dataset(simulate(table, 3), table, root / "table_data", "csv"), "static": static,
            "unlabelled": write_dataset(simulate(unlabelled, 3), unlabelled, root / "unlabelled_data", "csv-unlabelled")}
    out = {}
    for kind, path in data.items():
        out[kind] = root / kind
        run_dataset(path, out[kind])  # writes calibration.json and the certificate
        shutil.copy(out[kind] / CERTIFICATE, root / f"{kind}_as_run.html")
        write_certificate(out[kind])
    return out


@pytest.mark.parametrize("kind", ["table", "static", "unlabelled"])
def test_the_run_draws_the_page_its_files_give(runs, kind):
    """The run draws its certificate from the tables as it publishes them;
    ``rotcal certificate`` reads them back from the files: the same page."""
    assert (runs[kind].parent / f"{kind}_as_run.html").read_bytes() == (runs[kind] / CERTIFICATE).read_bytes()


@pytest.mark.parametrize("kind", ["table", "static", "unlabelled"])
def test_every_parameter_of_every_rate_with_its_U_and_k(runs, kind):
    cal = Calibration.read(runs[kind])
    page = _parsed(runs[kind])
    assert page.headings == SECTIONS
    assert len(page.rows) == len(cal.rates) * len(INTRINSIC)
    for rc in cal.rates:
        for q in rc.parameters:
            row = page.rows[(rc.rate_hz, q.name)]
            assert (row["value"], row["U"]) == gum_round(q.value, q.expanded_uncertainty)
            assert row["k"] == f"{q.coverage_factor:.2f}"
            # by hand: U to two significant digits, within half its last place; the value to the same place
            digits = row["U"].replace(".", "").lstrip("0")
            assert len(digits.rstrip("0") if "." not in row["U"] else digits) <= 2
            places = len(row["U"].partition(".")[2])
            assert len(row["value"].partition(".")[2]) == places
            assert abs(float(row["U"]) - q.expanded_uncertainty) <= 0.5 * 10.0 ** -places * (1 + 1e-9)
            assert abs(float(row["value"]) - q.value) <= 0.5 * 10.0 ** -places * (1 + 1e-9)
    assert 1.9 < min(float(r["k"]) for r in page.rows.values())


@pytest.mark.parametrize(("kind", "images"), [("table", 2), ("static", 1), ("unlabelled", 1)])
def test_page_references_nothing_outside_itself(runs, kind, images):
    page = _parsed(runs[kind])
    assert page.loads and all(v.startswith("data:image/png;base64,") for v in page.loads), page.loads
    assert page.images >= images
    assert not any("url(" in s or "@import" in s for s in page.styles)


def test_sections_follow_the_kind_of_run(runs):
    table, static, unlabelled = ((runs[k] / CERTIFICATE).read_text() for k in ("table", "static", "unlabelled"))
    assert "table segments" in table and "Gaitan &amp; Geist 2021 Figs. 6 and 7" in table
    assert "<td>uncertainty budget</td>" in table and "residual RMS before → after" in table
    assert "static poses" in static and "dut-7" in static
    poses = pl.read_parquet(runs["static"] / "poses.parquet").height
    assert f"every pose, dwell and segment ({poses})" in static and "Not applicable" in static
    dwells = pl.read_parquet(runs["unlabelled"] / "dwells.parquet").height
    assert "unlabelled recording" in unlabelled and f"<td>dwell</td><td class=\"num\">{dwells}</td>" in unlabelled
    # static poses are diagnosed (diagnose.static), and rotations without a table angle on their
    # reconstructed angles (issue 15 items 1 and 2): their findings tables are the section
    assert "This run was not diagnosed" not in static and "This run was not diagnosed" not in unlabelled
    assert "residual RMS before → after" in unlabelled


def test_optional_tables_absent_and_rerendered_by_the_command(runs, tmp_path, cli):
    run = tmp_path / "run"
    shutil.copytree(runs["table"], run)
    for name in ("uncertainty_budget", "diagnosis", "frequency_response", "fits", "segments"):
        (run / f"{name}.parquet").unlink()
    (run / "frequency_response.png").unlink()
    code, out, err = cli("certificate", run)
    assert code == 0 and "certificate written to" in out, err
    text = (run / CERTIFICATE).read_text()
    assert "<td>covariance, g_local apart</td>" in text and "<td>uncertainty budget</td>" not in text
    assert "This run was not diagnosed" in text
    assert "No pose, dwell or segment fit" in text
    # the same files give the same page, byte for byte
    shutil.copytree(runs["static"], tmp_path / "again")
    assert cli("certificate", tmp_path / "again")[0] == 0
    assert (tmp_path / "again" / CERTIFICATE).read_bytes() == (runs["static"] / CERTIFICATE).read_bytes()


def test_bad_run_directories_are_one_line_errors(runs, tmp_path, cli):
    code, _, err = cli("certificate", tmp_path)
    assert code == 2 and "calibration.json" in err and len(err.strip().splitlines()) == 1
    run = tmp_path / "broken"
    shutil.copytree(runs["static"], run)
    (run / "poses.parquet").write_bytes(b"not parquet")
    code, _, err = cli("certificate", run)
    assert code == 2 and "poses.parquet" in err and len(err.strip().splitlines()) == 1
    pl.DataFrame({"x": [1]}).write_parquet(run / "poses.parquet")
    with pytest.raises(InputError, match="not rotcal's poses table"):
        render(run)


def test_the_run_publishes_it_last_when_calibration_json_is_there(runs, tmp_path):
    assert [o.name for o in OUTPUTS[-2:]] == ["certificate", "certificate_pdf"]
    calibration = Calibration.read(runs["static"] / "calibration.json")
    item, _ = certificate_outputs(replace(RunConfig(), report=replace(RunConfig().report, figures=False)), calibration)
    assert item.draw(tmp_path, {}) is None  # no calibration.json: nothing to certify
    shutil.copy(runs["static"] / "calibration.json", tmp_path)
    path = item.draw(tmp_path, {})  # the tables this publish wrote: none
    assert path == tmp_path / CERTIFICATE and "<img" not in path.read_text()  # figures off: tables only
