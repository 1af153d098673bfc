"""One dataset in every capture form gives the same result; the same inputs
give the same outputs, bit for bit."""

import hashlib
import re

import numpy as np
import polars as pl
import pytest

from rotcal.run import run_dataset

from testdata import REPO


@pytest.mark.parametrize("fmt", ["mcap-cdr", "mcap-json"])
def test_mcap_gives_the_csv_result(make_dataset, tmp_path, fmt):
    """Issue 2 acceptance: CSV, MCAP with CDR and MCAP with JSON give the
    same intrinsic.parquet to 1e-9 relative."""
    run_dataset(make_dataset(21, "csv"), tmp_path / "csv")
    run_dataset(make_dataset(21, fmt), tmp_path / fmt)
    a = pl.read_parquet(tmp_path / "csv" / "intrinsic.parquet")
    b = pl.read_parquet(tmp_path / fmt / "intrinsic.parquet")
    assert a.select("rate_hz", "parameter").equals(b.select("rate_hz", "parameter"))
    for col in ("value", "std_uncertainty"):
        np.testing.assert_allclose(b[col].to_numpy(), a[col].to_numpy(), rtol=1e-9)
    segments = pl.read_parquet(tmp_path / fmt / "segments.parquet")
    assert set(segments["label_source"]) == {"table"}


def _digest(directory):
    """Every file's SHA-256; the listing's (rotcal-files.json) but for the time of the run, which it records."""
    return {p.relative_to(directory).as_posix(): hashlib.sha256(re.sub(rb'"run_time": "[^"]*"', b"", p.read_bytes())).hexdigest()
            for p in sorted(directory.rglob("*")) if p.is_file()}


def test_simulation_and_run_are_bit_for_bit_deterministic(cli, tmp_path, monkeypatch):
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")  # calibration.json's created_utc: the time of the run otherwise
    for k in ("a", "b"):
        assert cli("simulate", tmp_path / k / "data", "--seed", "9", "--effect", "rate_ripple:axis=y,ripple_deg=0.1")[0] == 0
        assert cli("run", tmp_path / k / "data", "--out", tmp_path / k / "out", "--quiet")[0] == 0
    assert _digest(tmp_path / "a" / "data") == _digest(tmp_path / "b" / "data")
    assert _digest(tmp_path / "a" / "out") == _digest(tmp_path / "b" / "out")
    produced = _digest(tmp_path / "a" / "out")
    assert {"intrinsic.parquet", "fits.parquet", "segments.parquet", "components.parquet",
            "diagnosis.parquet", "report.md"} <= set(produced)
    assert any(name.startswith("figures/") for name in produced)


def test_results_do_not_depend_on_the_number_of_workers(make_dataset, tmp_path, monkeypatch):
    import json

    from rotcal.config import RunConfig, RunSection

    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1700000000")
    run_dataset(make_dataset(22), tmp_path / "one", config=RunConfig(run=RunSection(workers=1)))
    run_dataset(make_dataset(22), tmp_path / "four", config=RunConfig(run=RunSection(workers=4)))
    one, four = _digest(tmp_path / "one"), _digest(tmp_path / "four")
    # the certificate shows the configuration and calibration.json's hash, the listing every file's
    for name in ("calibration.json", "certificate.html", "certificate.pdf", "rotcal-files.json"):
        assert one.pop(name) != four.pop(name)
    assert one == four
    # calibration.json records every configuration key, the worker count too: nothing else differs
    docs = [json.loads((tmp_path / k / "calibration.json").read_text()) for k in ("one", "four")]
    assert [d["configuration"].pop("run") for d in docs] == [{"workers": w, "stream_above_samples": 0} for w in (1, 4)] and docs[0] == docs[1]


def test_parquet_files_record_their_schema(make_dataset, tmp_path):
    from rotcal.tables import read_schema_name, schema

    run_dataset(make_dataset(22), tmp_path)
    for name in ("intrinsic", "fits", "segments", "components", "timebase"):
        assert read_schema_name(tmp_path / f"{name}.parquet") == (name, schema(name).version)


def test_demo_prints_the_summary(cli, tmp_path):
    status, out, err = cli("demo", "--dir", tmp_path)
    assert status == 0, err
    assert "value ± U (95 %)" in out and "k = 1.96 for every value" in out and "s_u" in out and "0.5 Hz" in out
    assert (tmp_path / "results" / "intrinsic.parquet").exists()


def test_ci_runs_the_readme_test_command():
    readme = (REPO / "README.md").read_text()
    commands = re.findall(r"```sh\n(.+?)\n```", readme)
    assert "rotcal demo" in commands[0] and "pytest" in commands[1]
    assert commands[1] in (REPO / ".ci" / "run").read_text()
