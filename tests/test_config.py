"""The run configuration's one definition (``rotcal.config``): the committed
schema and defaults file are the ones it writes, and every bound it states
refuses a file with one line naming the file and the key."""

import json
import math
import tomllib
from pathlib import Path

import pytest

from rotcal.config import RunConfig, generated_files, json_schema, load_config, with_options
from rotcal.errors import ConfigError, ExitCode

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name", sorted(generated_files()))
def test_committed_files_are_the_generated_ones(name):
    assert (REPO / name).read_text(encoding="utf-8") == generated_files()[name], \
        f"{name} is out of date: run `python -m rotcal.config` in the checkout"


def test_defaults_file_reads_back_as_the_defaults(tmp_path):
    path = REPO / "configs" / "defaults.toml"
    assert load_config(path) == load_config(None) == RunConfig()
    assert tomllib.loads(path.read_text())["run"]["workers"] == 0


def test_schema_states_each_default_and_bound():
    defs = json_schema()["$defs"]
    assert defs["FitConfig"]["properties"]["min_samples"] == {
        "default": 10, "description": "fewer samples in a segment: a failure row, not a fit", "minimum": 4, "type": "integer"}
    assert defs["DiagnosisConfig"]["properties"]["false_alarm"]["exclusiveMinimum"] == 0
    assert all(table["additionalProperties"] is False for table in defs.values())
    json.dumps(json_schema(), allow_nan=False)


@pytest.mark.parametrize("text, where", [
    ("[fit]\nmin_samples = 3", "fit.min_samples"),
    ("[fit]\nmin_span_deg = nan", "fit.min_span_deg"),
    ("[fit]\nmin_span_deg = -inf", "fit.min_span_deg"),
    ("[fit]\nsine_fit = 'five_parameter'", "fit.sine_fit"),
    ("[diagnosis]\nfalse_alarm = 0.0", "diagnosis.false_alarm"),
    ("[diagnosis]\nunexplained_false_alarm = inf", "diagnosis.unexplained_false_alarm"),
    ("[diagnosis]\nmax_samples = 999", "diagnosis.max_samples"),
    ("[uncertainty]\nmonte_carlo_max_draws = 19999", "uncertainty.monte_carlo_max_draws"),
    ("[limits]\nmax_line_bytes = '1 MiB'", "limits.max_line_bytes"),
    ("[report]\nfigures = 1", "report.figures"),
    ("[run]\nworkers = -1", "run.workers"),
    ("[run]\nthreads = 2", "run.threads"),
    ("workers = 2", "workers"),
    ("fit = 3", "fit"),
    ("[batch]\nexecutor = 'spark://x'", "batch.executor"),
])
def test_a_value_out_of_bounds_is_one_line_naming_file_and_key(tmp_path, text, where):
    path = tmp_path / "run.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    message = str(info.value)
    assert message.startswith(f"{path}: invalid configuration at {where}: ") and "\n" not in message
    assert info.value.exit_code == ExitCode.BAD_INPUT


def test_a_file_overrides_only_its_keys(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text("[fit]\nmin_span_deg = 45\n[batch]\nexecutor = 'dask://host:8786'\n")
    config = load_config(path)
    assert config.fit.min_span_deg == 45.0 and config.fit.min_samples == 10
    assert config.batch.executor == "dask://host:8786" and config.diagnosis == RunConfig().diagnosis
    assert math.isfinite(config.fit.min_span_deg)


def test_command_line_options_are_validated_as_the_file_is():
    assert with_options(RunConfig(), batch={"workers": 3}).batch.workers == 3
    with pytest.raises(ConfigError, match=r"^invalid configuration at batch\.workers: "):
        with_options(RunConfig(), batch={"workers": -2})
