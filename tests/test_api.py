"""The Python API (rotcal.api): its examples run (the module's doctests, the
README's and docs/api.md's code blocks), and it is the command line's
computation, not a second one."""

from __future__ import annotations

import doctest
import json
import re
from pathlib import Path

import polars as pl
import pytest

import rotcal
import rotcal.api
from rotcal.errors import InputError
from rotcal.run import run_dataset

ROOT = Path(__file__).resolve().parents[1]


def python_blocks(page: Path) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", page.read_text(encoding="utf-8"), flags=re.S | re.M)


def test_the_module_examples_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    outcome = doctest.testmod(rotcal.api, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert outcome.attempted >= 15
    assert outcome.failed == 0


@pytest.mark.parametrize("page", ["README.md", "docs/api.md"])
def test_the_pages_examples_run(page, tmp_path, monkeypatch, capsys):
    blocks = python_blocks(ROOT / page)
    assert blocks, f"{page} has no Python example"
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    for block in blocks:  # one page's blocks share a namespace, as in a notebook
        exec(compile(block, f"{page} example", "exec"), namespace)
    assert (tmp_path / "example" / "results" / "calibration.json").is_file()


@pytest.fixture(scope="module")
def reduced(tmp_path_factory):
    work = tmp_path_factory.mktemp("api")
    data = rotcal.simulate_dataset(work / "data", seed=3)
    return data, rotcal.calibrate(data, out=work / "results"), work


def test_the_api_writes_what_the_run_writes(reduced):
    data, result, work = reduced
    direct = run_dataset(data, work / "direct")
    assert sorted(result.tables) == sorted(p.stem for p in direct.written if p.suffix == ".parquet")
    for name in ("intrinsic", "fits", "uncertainty_budget"):
        assert result.table(name).equals(pl.read_parquet(work / "direct" / f"{name}.parquet")), name
    assert result.warnings == direct.warnings and result.notes == direct.notes


def test_the_parameters_agree_with_the_truth(reduced):
    data, result, _ = reduced
    truth = json.loads((data / "truth.json").read_text())["intrinsic"]
    frame = result.parameters()
    assert frame["recommended"].all() and frame.height == 9 * 5  # nine parameters, five rates
    for rate in result.calibration.rates:
        for name, true in truth.items():
            q = rate.parameter(name)
            row = frame.filter(rate_hz=rate.rate_hz, parameter=name)
            assert row["value"].item() == q.value
            assert abs(q.value - true) < 4 * q.std_uncertainty, (rate.rate_hz, name)


def test_correct_is_the_applied_correction(reduced):
    data, result, work = reduced
    applied = rotcal.apply_calibration(result.out, data, work / "applied.parquet")
    written = pl.read_parquet(applied.path)
    raw = rotcal.load_dataset(data).samples.select("u", "v", "w").to_numpy().T
    a = rotcal.correct(result.calibration, raw)
    assert applied.samples == raw.shape[1]
    assert (written.select("a_x", "a_y", "a_z").to_numpy().T == a).all()


def test_bad_input_is_rotcals_error(reduced, tmp_path):
    _, result, _ = reduced
    with pytest.raises(InputError, match="not a rotcal output directory"):
        rotcal.open_results(tmp_path)
    with pytest.raises(InputError, match="no table 'nope'"):
        result.table("nope")
    with pytest.raises(InputError, match="3 x n"):
        rotcal.correct(result.calibration, [[1.0, 2.0]])
    with pytest.raises(InputError, match="not an empty folder"):
        rotcal.simulate_dataset(result.out)
