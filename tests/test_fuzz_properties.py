"""Property-based tests of every input form (issue 17, docs/fuzzing.md):
for any value hypothesis draws into a CSV cell, a ``dataset.toml``, a run
configuration, a simulation request or an MCAP message, and any mutation of
``scripts/fuzz_inputs.py`` applied to a seed MCAP, rotcal either refuses the
input with one line naming the file (exit status 2) or reads it to finite
values; a neutral mutation (a comment, a dropped index) reads to the same
samples. Then the regressions of the defects ``scripts/fuzz.py`` found.

Hypothesis runs derandomized (the same examples every run) without an
example database, so the suite stays deterministic.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.writer import CompressionType, Writer
from polars.testing import assert_frame_equal

from rotcal.config import RunConfig, load_config
from rotcal.errors import ConfigError, ExitCode, InputError, RotcalError
from rotcal.ingest.formats.csv.reader import read_csv_capture
from rotcal.ingest.formats.mcap.reader import read_mcap_capture
from rotcal.ingest.meta import CsvFormat, load_meta
from rotcal.simulate import Plan, SimulationSpec, simulate, spec_from_toml, write_mcap
from rotcal.tables import finite_or_null

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import fuzz_inputs  # noqa: E402
from fuzz_seeds import floats  # noqa: E402

PROPERTY = settings(max_examples=60, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
LIMITS = RunConfig().limits


def finite(frame: pl.DataFrame) -> bool:
    return all(np.isfinite(floats(frame[c])).all() for c in frame.columns)


def one_line(exc: RotcalError, path: Path) -> None:
    """Refused as the CLI reports it: exit status 2, one line, naming the file."""
    assert exc.exit_code == ExitCode.BAD_INPUT
    assert "\n" not in exc.problem and exc.path == str(path), str(exc)


def loaded_or_refused(path: Path, doc: dict, load, error: type[RotcalError]):
    """``doc`` written to ``path`` as TOML and loaded: the result, or None when
    it is refused as the CLI reports it (``one_line``)."""
    path.write_text(toml_document(doc))
    try:
        return load(path)
    except error as exc:
        one_line(exc, path)
        return None


TEXT = st.one_of(st.sampled_from([t.decode("utf-8", "replace") for t in fuzz_inputs.HOSTILE_TEXT]),
                 st.text(max_size=30), st.floats().map(repr), st.integers().map(str))


@PROPERTY
@given(cells=st.lists(st.tuples(st.integers(0, 39), st.integers(0, 3), TEXT), min_size=1, max_size=4))
def test_any_csv_cell_is_refused_in_one_line_or_read_finite(tmp_path_factory, cells):
    rows = [[f"{k * 0.01:.2f}", str(100 + k), "-2.5", "981"] for k in range(40)]
    for row, column, text in cells:
        rows[row][column] = text
    path = tmp_path_factory.mktemp("csv") / "cells.csv"
    path.write_bytes(("t,u,v,w\n" + "".join(",".join(r) + "\n" for r in rows)).encode("utf-8", "surrogatepass"))
    try:
        frame = read_csv_capture(path, CsvFormat(), None, LIMITS)
    except InputError as exc:
        one_line(exc, path)
        return
    assert finite(frame)


CSV_SEED = "".join(f"{k * 0.06:.2f},{k % 7},{-k},{1000 + k}\n" for k in range(60))


@PROPERTY
@given(mutation=st.sampled_from([m for m in fuzz_inputs.CSV_WITH_HEADER if m.neutral]), seed=st.integers(0, 2**32))
def test_neutral_csv_mutations_read_to_the_same_samples(tmp_path_factory, mutation, seed):
    directory = tmp_path_factory.mktemp("neutral")
    (directory / "seed").mkdir()
    (directory / "mutated").mkdir()
    seed_file, mutated = directory / "seed" / "capture.csv", directory / "mutated" / "capture.csv"
    seed_file.write_text("t,u,v,w\n" + CSV_SEED)
    mutated.write_bytes(mutation.apply(seed_file.read_bytes(), np.random.default_rng(seed)))
    expected = read_csv_capture(seed_file, CsvFormat(), None, LIMITS)
    assert_frame_equal(read_csv_capture(mutated, CsvFormat(), None, LIMITS), expected)


def toml_value(value) -> str:
    """``value`` as TOML text (inline tables and arrays); NaN and Inf spelled as TOML spells them."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf") if math.isinf(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return '"' + "".join(c if c.isprintable() and c not in '"\\' else f"\\u{ord(c):04x}" for c in value) + '"'
    if isinstance(value, list):
        return "[" + ", ".join(map(toml_value, value)) + "]"
    return "{" + ", ".join(f'"{k}" = {toml_value(v)}' for k, v in value.items()) + "}"


SCALARS = st.one_of(st.floats(), st.integers(-(2**70), 2**70), st.booleans(), st.text(max_size=12),
                    st.sampled_from(["x", "y", "z", "whitespace", ";", "measured", "/imu", "acc.txt"]))
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=6), inner, max_size=3),
                      max_leaves=12)
DATASET_KEYS = {"site": ["g_local", "g_local_uncertainty"], "device": ["id", "output_unit", "full_scale"],
                "format": ["delimiter", "header", "names", "columns", "sample_rate_hz", "pose_column"],
                "plan": ["rates_hz"], "mcap": ["imu_topic", "table_topic"]}


def toml_document(tables: dict[str, dict]) -> str:
    return "".join(f"[{name}]\n" + "".join(f'"{k}" = {toml_value(v)}\n' for k, v in keys.items()) for name, keys in tables.items())


def documents(known: dict[str, list[str]]):
    """TOML documents of the tables ``known`` names, with known and unknown keys of any value."""
    keys = st.sampled_from([(t, k) for t, ks in known.items() for k in ks]) | st.tuples(st.sampled_from(list(known)), st.text(max_size=6))
    return st.lists(st.tuples(keys, VALUES), max_size=4).map(
        lambda pairs: {t: {k: v for (t2, k), v in pairs if t2 == t} for t in {t for (t, _), _ in pairs}})


@PROPERTY
@given(doc=documents(DATASET_KEYS))
def test_any_dataset_toml_is_refused_in_one_line_or_finite(tmp_path_factory, doc):
    meta = loaded_or_refused(tmp_path_factory.mktemp("meta") / "dataset.toml", doc, load_meta, InputError)
    if meta is None:
        return
    numbers = [meta.g_local, meta.g_local_uncertainty, *meta.plan_rates_hz, meta.full_scale or 0.0,
               meta.csv_format.sample_rate_hz or 0.0]
    assert all(isinstance(x, int | float) and math.isfinite(x) for x in numbers), meta


CONFIG_KEYS = {table: [f.name for f in getattr(RunConfig(), table).__dataclass_fields__.values()]
               for table in ("run", "fit", "uncertainty", "limits", "diagnosis", "batch")}


@PROPERTY
@given(doc=documents(CONFIG_KEYS))
def test_any_run_configuration_is_refused_in_one_line_or_finite(tmp_path_factory, doc):
    config = loaded_or_refused(tmp_path_factory.mktemp("config") / "config.toml", doc, load_config, ConfigError)
    if config is None:
        return
    values = [v for table in CONFIG_KEYS for v in vars(getattr(config, table)).values()]
    assert all(math.isfinite(v) for v in values if isinstance(v, float)), config


SIMULATION_KEYS = {"plan": ["step_deg", "step_samples", "rates_hz", "rotation_samples", "dt_s", "axes"],
                   "dut": ["sensitivity", "noise_std", "full_scale", "integer_output"],
                   "site": ["g_local", "g_local_uncertainty"], "timebase": ["drop_fraction", "jitter_s", "gap_count"]}


@PROPERTY
@given(doc=documents(SIMULATION_KEYS))
def test_any_simulation_request_is_refused_in_one_line_or_simulates_finite(tmp_path_factory, doc):
    base = {"plan": {"axes": ["x"], "rates_hz": [0.5], "rotation_samples": 40, "step_samples": 2, "step_deg": 90.0}}
    spec = loaded_or_refused(tmp_path_factory.mktemp("sim") / "request.toml",
                             {t: {**base.get(t, {}), **doc.get(t, {})} for t in {*base, *doc}}, spec_from_toml, ConfigError)
    if spec is None:
        return
    plan = spec.plan
    if len(plan.axes) * (360 / plan.step_deg * plan.step_samples + len(plan.rates_hz) * plan.rotation_samples) <= 5000:
        assert finite(simulate(spec, 1).samples.select(pl.selectors.float()))


@pytest.fixture(scope="module")
def seed_mcaps(tmp_path_factory) -> dict[str, Path]:
    spec = SimulationSpec(plan=Plan(axes=("x",), rates_hz=(0.5,), rotation_samples=60, step_samples=3, step_deg=90.0))
    sim = simulate(spec, 1)
    directory = tmp_path_factory.mktemp("mcap")
    return {encoding: write_mcap(sim, directory / f"{encoding}.mcap", encoding) for encoding in ("cdr", "json")}


def read_mcap(path: Path) -> pl.DataFrame:
    return read_mcap_capture(path, load_meta(None), None, LIMITS)[0].drop("capture")


@PROPERTY
@given(encoding=st.sampled_from(["cdr", "json"]), mutation=st.sampled_from(fuzz_inputs.MCAP), seed=st.integers(0, 2**32))
def test_any_mcap_mutation_is_refused_in_one_line_or_read_finite(tmp_path_factory, seed_mcaps, encoding, mutation, seed):
    path = tmp_path_factory.mktemp("mutated") / "capture.mcap"
    path.write_bytes(mutation.apply(seed_mcaps[encoding].read_bytes(), np.random.default_rng(seed)))
    try:
        samples = read_mcap(path)
    except InputError as exc:
        one_line(exc, path)
        return
    assert finite(samples)
    if mutation.neutral:
        assert_frame_equal(samples, read_mcap(seed_mcaps[encoding]))


JSON_VALUES = st.one_of(st.floats().map(lambda x: "NaN" if math.isnan(x) else "Infinity" if x == math.inf
                                        else "-Infinity" if x == -math.inf else repr(x)),
                        st.integers(-(10**30), 10**30).map(str), st.sampled_from([b.decode() for b in fuzz_inputs.HOSTILE_JSON]))


@PROPERTY
@given(field=st.sampled_from(["t", "u", "v", "w", "rate_hz", "angle_deg", "temperature_c"]), value=JSON_VALUES)
def test_any_json_message_value_is_refused_in_one_line_or_read_exactly(tmp_path_factory, field, value):
    path = tmp_path_factory.mktemp("json") / "dut.mcap"
    rows = [{"t": f"{k * 0.01:.2f}", "u": str(k), "v": "1.5", "w": "-2", "axis": '"x"', "rate_hz": "0.5", "angle_deg": str(k)}
            for k in range(20)]
    rows[7][field] = value
    with path.open("wb") as fh:
        writer = Writer(fh, compression=CompressionType.ZSTD)
        writer.start("", "property")
        channel = writer.register_channel("/imu", "json", writer.register_schema("s", "jsonschema", b"{}"))
        for k, row in enumerate(rows):
            writer.add_message(channel, k * 10**7, ("{" + ", ".join(f'"{n}": {v}' for n, v in row.items()) + "}").encode(), k * 10**7)
        writer.finish()
    try:
        samples = read_mcap(path)
    except InputError as exc:
        one_line(exc, path)
        return
    assert finite(samples)
    number = float(value)  # read, so a number: the one written
    if field == "t":  # messages are put in time order: the stamp is among the others
        assert round(number * 1e9) in samples["t_ns"].to_list()
    else:
        assert samples[field][7] == pytest.approx(number, rel=1e-12)


# -- regressions of the defects the fuzzer found (each failed before its fix) -----------

@pytest.mark.parametrize("text", [b"[run]\nworkers = 1  # \xff\n", b"x = " + b"[" * 2000 + b"]" * 2000 + b"\n",
                                  b"[run]\nworkers = " + b"9" * 5000 + b"\n"])
def test_a_configuration_not_utf8_nested_or_with_a_huge_integer_is_one_line(tmp_path, text):
    path = tmp_path / "config.toml"
    path.write_bytes(text)
    with pytest.raises(ConfigError) as error:
        load_config(path)
    one_line(error.value, path)


SIMULATION_REQUEST = '[plan]\naxes = ["x"]\nrates_hz = [0.5]\nrotation_samples = 40\nstep_samples = 2\n'


@pytest.mark.parametrize(("extra", "needle"), [
    ('[[effect]]\nname = "axis_tilt"\naxis = "x"\ntilt_de = 0.3\n', "unknown parameter 'tilt_de'"),
    ('[[effect]]\nname = "axis_tilt"\ntilt_deg = 0.3\n', "axis"),
    ("[site]\ng_local = nan\n", "g_local = nan must be a finite number"),
    ("[site]\ng_local = { a = 1 }\n", "g_local"),
    ("[dut]\nfull_scale = -9223372036854775809\n", "full_scale"),
    ('[timebase]\ndrop_fraction = "x"\n', "drop_fraction = 'x' must be a finite number"),
    ("[timebase]\njitter_s = nan\n", "jitter_s = nan must be a finite number"),
    ("[plan]\nrates_hz = 1\n", "rates_hz"),
    ("[plan]\naxes = 1.5\n", "axes = 1.5 must be a non-empty list"),
    ("[plan]\ndt_s = 1e-320\n", "dt_s = 1e-320 must be at least 1e-9 s"),
])
def test_a_bad_simulation_request_is_refused_naming_the_file(tmp_path, extra, needle):
    path = tmp_path / "request.toml"
    path.write_text(extra if extra.startswith("[plan]") else SIMULATION_REQUEST + extra)
    with pytest.raises(ConfigError) as error:
        spec_from_toml(path)
    one_line(error.value, path)
    assert needle in error.value.problem


def test_a_failed_fits_nan_covariance_is_published_as_nulls():
    frame = pl.DataFrame({"cov_u": [[1.0, float("nan"), float("inf")], [2.0, 3.0, 4.0]], "C": [float("nan"), 1.0]})
    published = finite_or_null(frame)
    assert published["cov_u"].to_list() == [[1.0, None, None], [2.0, 3.0, 4.0]]
    assert published["C"].to_list() == [None, 1.0]


def test_a_capture_name_too_long_for_the_file_system_is_one_line(tmp_path):
    from rotcal.ingest.dataset import load_dataset

    (tmp_path / "dataset.toml").write_text(f'[[capture]]\nfile = "{"x" * 10000}.csv"\n')
    with pytest.raises(InputError) as error:
        load_dataset(tmp_path)
    assert "does not exist" in str(error.value) and "\n" not in str(error.value)


@pytest.mark.parametrize("kept", [5, 1])
def test_a_labelled_rotation_cut_short_without_angle_fails_its_fit_instead_of_nan(tmp_path, kept):
    """Its own-phase fit has ten parameters: from five samples the inverse
    information matrix had negative variances, published as NaN
    uncertainties of an "ok" fit (fuzz seed 17, input 35260); from one, the
    spectral search raised ValueError (input 63580)."""
    from rotcal.ingest.dataset import load_dataset
    from rotcal.run import segment_and_fit
    from rotcal.simulate import write_dataset

    spec = SimulationSpec(plan=Plan(rates_hz=(0.5,), rotation_samples=120, step_samples=5, step_deg=45.0))
    directory = write_dataset(simulate(spec, 1), spec, tmp_path / "cut")
    rotation = directory / "03_y_0.5hz.csv"
    lines = rotation.read_text().splitlines()[: kept + 1]
    lines[kept] = lines[kept].rsplit(",", 1)[0] + ","  # the file cut inside its last angle
    rotation.write_text("\n".join(lines))
    seg = segment_and_fit(load_dataset(directory), RunConfig())
    cut = seg.fits.filter(pl.col("segment") == seg.segments.filter(pl.col("n_samples") == kept)["segment"][0])
    assert cut["status"].to_list() == ["failed"] * 3
    assert "not determined" in cut["reason"][0]
    ok = seg.fits.filter(pl.col("status") == "ok").select("C", "A", "B", "u_C", "u_A", "u_B", "sigma")
    assert finite(ok) and ok.height == 15
