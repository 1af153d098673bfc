"""rotcal from Python: notebooks and other programs.

A thin layer over the functions the command line calls (``run_dataset``,
``apply_calibration``, ``export_calibration``): the same computation, the
same output directory, the same errors (``rotcal.errors.RotcalError`` and
its subclasses, where the command line prints one line and exits 2 or 3).
Results are read back as typed records (``Calibration``, ``RateCalibration``,
``Quantity``: frozen dataclasses with value, standard uncertainty, degrees of
freedom, coverage factor and expanded uncertainty) and as polars frames of
the published Parquet tables (their columns are documented in
``schemas/`` and on the outputs page).

Examples
--------
A simulated dataset (the test plan of Gaitan & Geist 2021, seeded: the same
seed gives the same numbers), reduced:

>>> import tempfile
>>> from pathlib import Path
>>> import rotcal
>>> work = Path(tempfile.mkdtemp())
>>> data = rotcal.simulate_dataset(work / "data", seed=1)
>>> result = rotcal.calibrate(data, out=work / "results")
>>> result.recommended_model
'baseline'
>>> frame = result.parameters().filter(rate_hz=0.0)
>>> frame.columns[:8]
['dataset', 'model', 'recommended', 'rate_hz', 'parameter', 'value', 'std_uncertainty', 'dof']
>>> [(row["parameter"], round(row["value"], 1)) for row in frame.head(3).iter_rows(named=True)]
[('s_u', 1670.6), ('s_v', 1666.4), ('s_w', 1670.2)]

The calibration as typed records: a parameter with its uncertainty, P and O
of a = P (R - O):

>>> dc = result.calibration.rate(0.0)
>>> s_u = dc.parameter("s_u")
>>> s_u.unit, round(s_u.coverage_factor, 2)
('bit/(m/s^2)', 1.96)
>>> dc.P_matrix.shape, dc.O_vector.shape
((3, 3), (3,))

A recording calibrated, in memory or to a file, and the calibration
exported for a flight stack:

>>> a = rotcal.correct(result.calibration, [[1000.0], [0.0], [0.0]])
>>> a.shape
(3, 1)
>>> applied = rotcal.apply_calibration(result.out, data, work / "calibrated.parquet")
>>> applied.samples > 0, applied.frame == dc.frame
(True, True)
>>> print(rotcal.export_calibration(result.calibration, "json").text[:1])
{

A run's output directory written earlier (by ``rotcal run``, say) opens
the same way:

>>> rotcal.open_results(work / "results").files == result.files
True
>>> import shutil
>>> shutil.rmtree(work)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.apply import Applied, Export
from rotcal.apply import apply_calibration as _apply
from rotcal.apply import correct as _correct
from rotcal.apply import export_calibration as _export
from rotcal.config import RunConfig, load_config, with_options
from rotcal.errors import InputError
from rotcal.model.calibration import Calibration, Quantity, RateCalibration

# named so as not to shadow rotcal's subpackages (rotcal.run, rotcal.apply, rotcal.simulate)
__all__ = ["Applied", "Calibration", "Export", "Quantity", "RateCalibration", "Recording", "Result", "apply_calibration",
           "calibrate", "correct", "export_calibration", "load_calibration", "load_dataset", "open_results",
           "simulate_dataset"]

LISTING = "rotcal-files.json"  # the run's own listing of what it wrote (report.publish)


@dataclass(frozen=True)
class Recording:
    """A dataset as rotcal reads it: its name, the DUT's output unit, the
    canonical sample table (``t_ns``, ``u``, ``v``, ``w`` and the labels
    the input carries or implies) and notes on what ingest assumed."""

    name: str
    output_unit: str
    samples: pl.DataFrame
    notes: tuple[str, ...]


@dataclass(frozen=True)
class Result:
    """A run's results, read from its output directory ``out``.

    ``calibration`` is ``calibration.json`` as typed records: per rate the
    recommended model, why, the nine parameters and P, Q, O with their
    covariances. ``warnings`` and ``notes`` are the run's (empty when the
    results were opened from a directory). Every published table is a
    polars frame through ``table``.
    """

    out: Path
    calibration: Calibration
    files: tuple[str, ...]
    warnings: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()

    @property
    def recommended_model(self) -> str:
        """The model ``calibration.json`` recommends (the same for every rate)."""
        return self.calibration.rates[0].model

    @property
    def tables(self) -> tuple[str, ...]:
        """The names of the Parquet tables the run wrote (``intrinsic``, ``fits``, ...)."""
        return tuple(Path(f).stem for f in self.files if f.endswith(".parquet"))

    def table(self, name: str) -> pl.DataFrame:
        """The published table ``name`` (``intrinsic``, ``diagnosis``, ...) as a polars frame."""
        if name not in self.tables:
            raise InputError(f"this run wrote no table {name!r} (it wrote {', '.join(self.tables)})", path=self.out)
        return pl.read_parquet(self.out / f"{name}.parquet")

    def parameters(self, model: str = "recommended") -> pl.DataFrame:
        """The nine intrinsic parameters per rate of ``model`` (``recommended``,
        ``baseline``, ``refined``, ``orthogonal``): value, standard and
        expanded uncertainty, coverage factor, degrees of freedom."""
        intrinsic = self.table("intrinsic")
        rows = intrinsic.filter(pl.col("recommended") if model == "recommended" else pl.col("model") == model)
        if rows.is_empty():
            raise InputError(f"no {model!r} parameters in this run (models: "
                             f"{', '.join(intrinsic['model'].unique(maintain_order=True))})", path=self.out)
        return rows

    def findings(self) -> pl.DataFrame:
        """The diagnosis's detected effects and unexplained structure (empty
        when nothing was found or the run was not diagnosed)."""
        if "diagnosis" not in self.tables:
            return pl.DataFrame()
        return self.table("diagnosis").filter(pl.col("detected"))


def simulate_dataset(directory: str | Path, seed: int = 1, effects: Sequence[str] = (), fmt: str = "csv") -> Path:
    """Write a synthetic dataset (the Gaitan & Geist 2021 test plan), as
    ``rotcal simulate DIR`` does, with its ``truth.json``; return its folder.

    Parameters
    ----------
    directory
        where to write it; created, and refused if it holds anything.
    seed
        random seed: the same seed gives the same files.
    effects
        effects of the catalogue switched on, ``NAME:key=value,...``
        (e.g. ``centripetal:axis=y,radius_m=0.22``).
    fmt
        ``csv``, ``csv-unlabelled``, ``mcap-cdr`` or ``mcap-json``.
    """
    from rotcal.simulate import SimulationSpec, write_dataset
    from rotcal.simulate import simulate as simulated

    directory = Path(directory)
    if directory.exists() and (not directory.is_dir() or any(directory.iterdir())):
        raise InputError("not an empty folder: a simulated dataset needs one of its own", path=directory)
    spec = SimulationSpec().with_effects(*effects)
    write_dataset(simulated(spec, seed), spec, directory, fmt)
    return directory


def load_dataset(dataset: str | Path, meta: str | Path | None = None) -> Recording:
    """Read a dataset (a directory of captures, or one capture file) as
    ``rotcal run`` does, without reducing it. ``meta``: its ``dataset.toml``
    kept elsewhere."""
    from rotcal.ingest.dataset import load_dataset as read

    ds = read(Path(dataset), None if meta is None else Path(meta))
    return Recording(ds.name, ds.meta.output_unit, ds.samples, ds.notes)


def calibrate(dataset: str | Path, out: str | Path, meta: str | Path | None = None,
        config: str | Path | RunConfig | None = None, workers: int | None = None) -> Result:
    """Reduce a dataset, as ``rotcal run DATASET --out OUT`` does, and return
    its results.

    Parameters
    ----------
    dataset
        a directory of captures (``*.csv``, ``*.mcap``) with an optional
        ``dataset.toml``, or one capture file.
    out
        the output directory: holds this run alone afterwards (a directory
        holding files no rotcal listing names is refused).
    meta
        the dataset's ``dataset.toml`` kept outside it.
    config
        a run configuration: a TOML file overriding ``configs/defaults.toml``,
        or a ``RunConfig``.
    workers
        cores the run uses (0: every core it may run on).

    Raises
    ------
    rotcal.errors.InputError
        unreadable input or an unusable output directory.
    rotcal.errors.UndeterminedError
        what the recording holds determines no result.
    """
    from rotcal.report.publish import OutputDir, check_out
    from rotcal.run import run_dataset

    cfg = config if isinstance(config, RunConfig) else load_config(None if config is None else Path(config))
    if workers is not None:
        cfg = with_options(cfg, run={"workers": workers})
    target = check_out(OutputDir(Path(out)), (Path(dataset), None if meta is None else Path(meta)), True)
    outcome = run_dataset(Path(dataset), target, None if meta is None else Path(meta), cfg)
    return replace(open_results(out), warnings=outcome.warnings, notes=outcome.notes)


def open_results(out: str | Path) -> Result:
    """The results of a run published earlier in ``out`` (``rotcal run``,
    ``rotcal batch``'s per-dataset folders, ``rotcal demo``'s ``results/``)."""
    import json

    out = Path(out)
    try:
        listing = json.loads((out / LISTING).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise InputError(f"not a rotcal output directory ({LISTING}: {exc})", path=out) from None
    return Result(out, Calibration.read(out), tuple(f["name"] for f in listing["files"]))


def load_calibration(path: str | Path) -> Calibration:
    """``calibration.json`` (or a run's output directory holding one) as typed records."""
    return Calibration.read(Path(path))


def correct(calibration: Calibration, raw: np.ndarray | Sequence[Sequence[float]], rate_hz: float | None = None) -> np.ndarray:
    """a = P (R - O) (Geist 2017 Eq. 18): ``raw`` (3 x n, rows u, v, w in
    output units) in m/s^2 in the calibration's frame, with the entry of
    ``rate_hz`` (None: DC)."""
    rc = calibration.rate(rate_hz)
    samples = np.asarray(raw, dtype=float)
    if samples.ndim != 2 or samples.shape[0] != 3:
        raise InputError(f"raw samples must be 3 x n (rows u, v, w), not {samples.shape}")
    return _correct(samples, rc.P_matrix, rc.O_vector)


def apply_calibration(calibration: str | Path, recording: str | Path, out: str | Path, rate_hz: float | None = None,
          uncertainty: bool = False, meta: str | Path | None = None) -> Applied:
    """Calibrate a recording into ``out`` (``.parquet``, ``.csv`` or ``.mcap``),
    as ``rotcal apply`` does; ``uncertainty``: each sample's standard
    uncertainty from the calibration's covariance."""
    return _apply(Path(calibration), Path(recording), Path(out), rate_hz, uncertainty,
                             None if meta is None else Path(meta))


def export_calibration(calibration: Calibration | str | Path, fmt: str, rate_hz: float | None = None,
           nominal_scale: float | None = None) -> Export:
    """The calibration in a flight stack's or tool's form (``ardupilot``,
    ``px4``, ``yaml``, ``json``), as ``rotcal export`` writes it; its
    ``warnings`` say what the form cannot hold, ``write(path)`` saves it."""
    cal = calibration if isinstance(calibration, Calibration) else Calibration.read(Path(calibration))
    return _export(cal, fmt, rate_hz, nominal_scale)
