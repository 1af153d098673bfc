"""calibration.json as a run writes it (issue 14): schema-valid, the
refined model recommended where the diagnosis modelled an effect (and the
model-dependent tables then of that model), the inputs' hashes against
hashlib, and bit-identical reruns under SOURCE_DATE_EPOCH."""

from __future__ import annotations

import hashlib
import json

import polars as pl
import pytest
from typer.testing import CliRunner

from rotcal.cli import app
from rotcal.model.calibration import Calibration
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.spec import Plan

SPEC = SimulationSpec(plan=Plan(rates_hz=(0.1, 0.5)))
EPOCH = "1700000000"  # 2023-11-14T22:13:20Z


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """A dataset with a 3 ms delay of channel v and a clean one, each run
    once (the clean one twice) with SOURCE_DATE_EPOCH set."""
    tmp = tmp_path_factory.mktemp("calibration_json")
    delayed = SPEC.with_effects("channel_delay:delay_v_s=0.003")
    data = {"delay": write_dataset(simulate(delayed, 5), delayed, tmp / "delay"),
            "clean": write_dataset(simulate(SPEC, 6), SPEC, tmp / "clean")}
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SOURCE_DATE_EPOCH", EPOCH)
        for name, path in data.items():
            run_dataset(path, tmp / f"{name}_out")
        run_dataset(data["clean"], tmp / "clean_again")
    return tmp


def _model_rows(out, table: str) -> set[str]:
    return set(pl.read_parquet(out / f"{table}.parquet")["model"].to_list())


def test_effect_found_recommends_the_refined_model_everywhere(runs):
    out = runs / "delay_out"
    cal = Calibration.read(out)  # validates against schemas/calibration.json
    assert {r.model for r in cal.rates} == {"refined"} and "channel_delay" in cal.rates[0].reason
    intrinsic = pl.read_parquet(out / "intrinsic.parquet")
    recommended = intrinsic.filter(pl.col("recommended"))
    assert set(recommended["model"]) == {"refined"} and recommended.height == 9 * len(cal.rates)
    for rate in cal.rates:
        rows = recommended.filter(pl.col("rate_hz") == rate.rate_hz)
        assert [q.value for q in rate.parameters] == rows["value"].to_list()
        assert [q.expanded_uncertainty for q in rate.parameters] == pytest.approx(rows["expanded_uncertainty"].to_list(), rel=1e-12)
    for table in ("frequency_response", "consistency", "cross_sensitivity"):
        assert _model_rows(out, table) == {"refined"}, table
    # the truth has no angle change with rate: under the refined model none is
    # left (the baseline reads the delay as phi_uv falling 2 pi f tau = 540 mdeg
    # at 0.5 Hz); 4u, as the six differences share the DC result's noise
    angles = pl.read_parquet(out / "frequency_response.parquet").filter(pl.col("quantity") == "angle_deviation")
    assert angles.height == 6 and (angles["value"].abs() < 4 * angles["std_uncertainty"]).all()
    assert pl.read_parquet(out / "consistency.parquet")["consistent"].all()


def test_clean_dataset_recommends_the_baseline(runs):
    out = runs / "clean_out"
    cal = Calibration.read(out / "calibration.json")
    assert {(r.model, r.reason) for r in cal.rates} == {("baseline", "the diagnosis found no effect to model")}
    intrinsic = pl.read_parquet(out / "intrinsic.parquet")
    assert intrinsic["recommended"].to_list() == (intrinsic["model"] == "baseline").to_list()
    assert _model_rows(out, "frequency_response") == {"baseline"}
    assert cal.g_local_source == "dataset.toml [site]" and cal.created_utc == "2023-11-14T22:13:20Z"
    assert cal.configuration["diagnosis"]["enabled"] is True


def test_input_hashes_are_the_files_sha256(runs):
    data = runs / "clean"
    inputs = Calibration.read(runs / "clean_out").inputs
    files = sorted(p for p in data.iterdir() if p.suffix in (".csv", ".toml"))
    assert sorted(i["path"] for i in inputs) == [p.name for p in files]
    for entry in inputs:
        raw = (data / entry["path"]).read_bytes()
        assert entry["sha256"] == hashlib.sha256(raw).hexdigest() and entry["bytes"] == len(raw)


def test_reruns_are_bit_identical_under_source_date_epoch(runs):
    first, second = runs / "clean_out", runs / "clean_again"
    assert (first / "calibration.json").read_bytes() == (second / "calibration.json").read_bytes()
    assert (first / "intrinsic.parquet").read_bytes() == (second / "intrinsic.parquet").read_bytes()


def test_run_json_prints_the_recommended_result(runs, tmp_path):
    result = CliRunner().invoke(app, ["run", str(runs / "delay"), "--out", str(tmp_path), "--json"])
    assert result.exit_code == 0, result.output
    doc = json.loads(result.stdout)
    cal = Calibration.read(tmp_path)
    assert doc["exit_status"] == 0 and doc["model"] == "refined"
    assert [p["value"] for r in doc["rates"] for p in r["parameters"]] == [q.value for r in cal.rates for q in r.parameters]
    assert str(tmp_path / "calibration.json") in doc["written"]
