"""The fuzzer's seed inputs, one per input form, and how each form is run
and checked (``scripts/fuzz.py``, docs/fuzzing.md).

Every seed is written from one tiny seeded simulation (480 samples: three
axes, a 45 degree step sequence and one 0.5 Hz rotation each), so that the
ingest, time-base, segmentation and fit stages take milliseconds and a full
``run_dataset`` under a second.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path

import fuzz_inputs as fi
import numpy as np
import polars as pl

TINY_PLAN = dict(rates_hz=(0.5,), rotation_samples=120, step_samples=5, step_deg=45.0)
SIMULATION_REQUEST = """\
output_unit = "bit"

[plan]
axes = ["x", "y"]
rates_hz = [0.5]
rotation_samples = 100
step_samples = 4
step_deg = 90.0
dt_s = 0.06

[dut]
sensitivity = 1669.0
noise_std = 8.0
full_scale = 32767.0

[site]
g_local = 9.80101
g_local_uncertainty = 3e-5

[timebase]
drop_fraction = 0.01
jitter_s = 0.001

[[effect]]
name = "axis_tilt"
axis = "x"
tilt_deg = 0.3
"""
MAX_SIMULATED = 20_000  # samples a mutated request may ask for and still be simulated


@dataclass(frozen=True, eq=False)
class Result:
    """What one input gave: the tables to compare, the non-finite values
    found (``table.column`` names), and whether a full run was undetermined."""

    tables: dict = field(default_factory=dict)
    nonfinite: str = ""
    undetermined: bool = False


def floats(series: pl.Series) -> np.ndarray:
    """Every float in a column, nested lists, arrays and structs included (nulls left out)."""
    if isinstance(series.dtype, pl.List):
        return floats(series.explode())
    if isinstance(series.dtype, pl.Array):
        return floats(series.arr.explode())
    if isinstance(series.dtype, pl.Struct):
        return np.concatenate([floats(series.struct.field(f)) for f in series.struct.fields] or [np.zeros(0)])
    return series.drop_nulls().to_numpy() if series.dtype.is_float() else np.zeros(0)


def nonfinite(tables: dict[str, pl.DataFrame]) -> str:
    return ", ".join(f"{name}.{c}" for name, frame in tables.items() for c in frame.columns
                     if not np.isfinite(floats(frame[c])).all())


def _config(path: Path | None = None):
    from rotcal.config import load_config, with_options

    return with_options(load_config(path), run={"workers": 1}, report={"figures": False},
                        diagnosis={"report": False})


def run_dataset_form(directory: Path, config=None, full: bool = False, out: Path | None = None) -> Result:
    """The ingest, time-base, segmentation and fit stages in-process; with
    ``full``, ``run_dataset`` too, every table it publishes read back."""
    from rotcal.errors import UndeterminedError
    from rotcal.ingest.dataset import load_dataset
    from rotcal.run import run_dataset, segment_and_fit
    from rotcal.tables import conform, finite_or_null

    config = config or _config()
    ds = load_dataset(directory, None, config.limits, 1)
    seg = segment_and_fit(ds, config)
    tables = {"samples": ds.samples, **{t.name: t.data for t in seg.tables}}
    # the tables as they would be published, and a fit "ok" only with finite numbers
    ok = seg.fits.filter(pl.col("status") == "ok").select("C", "A", "B", "u_C", "u_A", "u_B", "sigma")
    bad = nonfinite({"samples": ds.samples, "ok fits": ok,
                     **{t.name: finite_or_null(conform(t.data, t.name)) for t in seg.tables}})
    undetermined = False
    if full and not bad and out is not None:
        import shutil

        shutil.rmtree(out, ignore_errors=True)
        try:
            run_dataset(directory, out, None, config)
        except UndeterminedError:
            undetermined = True
        bad = nonfinite({p.stem: pl.read_parquet(p) for p in sorted(out.glob("*.parquet"))})
    return Result(tables, bad, undetermined)


def same_tables(reference: Result, result: Result, renamed: dict[str, str]) -> bool:
    """The tables equal, capture names mapped back where a file was renamed."""
    if reference.tables.keys() != result.tables.keys():
        return False
    for name, frame in result.tables.items():
        if renamed and "capture" in frame.columns:
            frame = frame.with_columns(pl.col("capture").cast(pl.String).replace(renamed))
            ref = reference.tables[name].with_columns(pl.col("capture").cast(pl.String))
        else:
            ref = reference.tables[name]
        if not frame.equals(ref):
            return False
    return True


@dataclass(frozen=True)
class Form:
    """An input form: its seed directory (``name`` under the seeds), the files
    mutated (``target``, a glob), its mutations, and how it is run and compared."""

    name: str
    target: str
    mutations: tuple[fi.Mutation, ...]
    renamable: bool = False
    kind: str = "dataset"

    def run(self, directory: Path, seeds: Path, full: bool, out: Path) -> Result:
        if self.kind == "config":
            return run_dataset_form(seeds / "csv-unlabelled", _config(directory / "config.toml"), full, out)
        if self.kind == "simulation":
            return simulate_form(directory / "request.toml")
        return run_dataset_form(directory, None, full, out)

    def same(self, reference: Result, result: Result, renamed: dict[str, str]) -> bool:
        return same_tables(reference, result, renamed)


def simulate_form(path: Path) -> Result:
    """A simulation request: read (``spec_from_toml``) and, when it asks for
    at most ``MAX_SIMULATED`` samples, simulated; the spec and the samples."""
    from rotcal.simulate import simulate, spec_from_toml

    spec = spec_from_toml(path)
    plan = spec.plan
    try:
        size = len(plan.axes) * (360 / plan.step_deg * plan.step_samples + len(plan.rates_hz) * plan.rotation_samples)
    except OverflowError:  # counts beyond floats: far too large to simulate
        size = math.inf
    tables = {"spec": pl.DataFrame({"spec": [repr(dataclasses.asdict(spec))]})}
    if plan.continuous or size > MAX_SIMULATED:
        return Result(tables)
    samples = simulate(spec, 1).samples
    tables["samples"] = samples
    return Result(tables, nonfinite({"samples": samples}))


FORMS = (
    Form("csv-labelled", "*.csv", fi.CSV_WITH_HEADER, renamable=True),
    Form("csv-unlabelled", "*.csv", fi.CSV_WITH_HEADER, renamable=True),
    Form("csv-whitespace", "*.txt", fi.CSV),
    Form("csv-mapped", "*.csv", fi.CSV),
    Form("csv-rate", "*.csv", fi.CSV),
    Form("mcap-cdr", "*.mcap", fi.MCAP, renamable=True),
    Form("mcap-json", "*.mcap", fi.MCAP, renamable=True),
    Form("dataset-toml", "dataset.toml", fi.TOML),
    Form("config-toml", "config.toml", fi.TOML, kind="config"),
    Form("simulation-toml", "request.toml", fi.TOML, kind="simulation"),
)


def build_seeds(root: Path) -> Path:
    """Every form's seed directory under ``root`` (deterministic)."""
    from rotcal.config import toml_text
    from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

    spec = SimulationSpec(plan=Plan(**TINY_PLAN))
    sim = simulate(spec, 1)
    for fmt in ("csv", "csv-unlabelled", "mcap-cdr", "mcap-json"):
        write_dataset(sim, spec, root / {"csv": "csv-labelled"}.get(fmt, fmt), fmt)
    recording = pl.read_csv(root / "csv-unlabelled" / "recording.csv")
    site = '[site]\ng_local = 9.80101\ng_local_uncertainty = 3e-5\n'

    def dataset(name: str, text: str, toml: str, file: str) -> None:
        (root / name).mkdir(parents=True)
        (root / name / file).write_text(text)
        (root / name / "dataset.toml").write_text(toml)

    dataset("csv-whitespace", "".join(f"  {t:.7e}   {u}\t{v}  {w}\n" for t, u, v, w in recording.iter_rows()),
            f'{site}\n[format]\ndelimiter = "whitespace"\nheader = false\nnames = ["t", "u", "v", "w"]\n'
            '\n[[capture]]\nfile = "acc.txt"\n', "acc.txt")
    dataset("csv-mapped", "# logger export\ntime;acc_x;acc_y;acc_z;note\n"
            + "".join(f"{t};{u};{v};{w};ok\n" for t, u, v, w in recording.iter_rows()),
            f'{site}\n[format]\ndelimiter = ";"\ncolumns = {{ t = "time", u = "acc_x", v = "acc_y", w = "acc_z" }}\n', "log.csv")
    dataset("csv-rate", "u\tv\tw\n" + "".join(f"{u}\t{v}\t{w}\n" for _, u, v, w in recording.iter_rows()),
            f'{site}\n[format]\ndelimiter = "tab"\nsample_rate_hz = {1 / spec.plan.dt_s!r}\n', "rate.csv")
    labelled = root / "csv-labelled"
    (root / "dataset-toml").mkdir()
    captures = ""
    for csv in sorted(labelled.glob("*.csv")):
        (root / "dataset-toml" / csv.name).write_bytes(csv.read_bytes())
        axis, rate = csv.stem.split("_")[1:]
        captures += f'\n[[capture]]\nfile = "{csv.name}"\naxis = "{axis}"\nrate_hz = {0.0 if rate == "static" else 0.5}\n'
    (root / "dataset-toml" / "dataset.toml").write_text(
        f'angle_source = "commanded"\n\n[device]\nid = "dut-1"\noutput_unit = "bit"\nfull_scale = 32767\n\n{site}'
        f'\n[mcap]\nimu_topic = "/imu"\n\n[plan]\nrates_hz = [0.5]\n{captures}')
    (root / "config-toml").mkdir()
    (root / "config-toml" / "config.toml").write_text(toml_text())
    (root / "simulation-toml").mkdir()
    (root / "simulation-toml" / "request.toml").write_text(SIMULATION_REQUEST)
    return root
