"""MATLAB captures (``rotcal.ingest.formats.mat``): a seeded simulated
dataset saved with ``scipy.io.savemat`` as MATLAB writes its variables
(row vectors, a character array of axis labels, or one N x 4 matrix) gives
the samples and the run's tables of the same data as CSV; what is not a
usable MATLAB capture is refused in one line naming the file."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import scipy.io
from polars.testing import assert_frame_equal

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset, read_capture
from rotcal.ingest.formats.csv.writer import write_samples
from rotcal.ingest.meta import load_meta
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset

SPEC = SimulationSpec()
SPEC = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=600, rates_hz=(0.2, 1.0)))


@pytest.fixture(scope="module")
def samples() -> pl.DataFrame:
    """A seeded simulation of the default plan's steps and two rates, every sample labelled."""
    return simulate(SPEC, 11).samples.filter(pl.col("axis").is_not_null())


def as_matlab(samples: pl.DataFrame) -> dict[str, np.ndarray]:
    """The variables as a MATLAB user saves them: row vectors of doubles, the axis labels a char array."""
    return {"t": (samples["t_ns"].to_numpy() / 1e9)[None, :], **{c: samples[c].to_numpy()[None, :] for c in "uvw"},
            "axis": np.array(samples["axis"].cast(pl.String).to_list()),
            "rate_hz": samples["rate_hz"].to_numpy()[None, :], "angle_deg": samples["angle_deg"].to_numpy()[None, :]}


def test_the_samples_are_the_csv_routes(tmp_path, samples):
    scipy.io.savemat(tmp_path / "capture.mat", as_matlab(samples))
    write_samples(samples, tmp_path / "capture.csv")
    meta = load_meta(None)
    mat, _ = read_capture(tmp_path / "capture.mat", None, meta, Limits())
    csv, _ = read_capture(tmp_path / "capture.csv", None, meta, Limits())
    assert mat.height == samples.height and mat["axis"].null_count() == 0
    assert_frame_equal(mat.drop("capture"), csv.drop("capture"))  # exact


def test_a_matrix_of_time_and_outputs(tmp_path, samples):
    """One N x 4 matrix [t u v w] (any name), saved as MATLAB's column-major
    matrix or transposed, with the capture's axis as one character."""
    one = samples.filter(pl.col("axis") == "x")
    matrix = np.column_stack([one["t_ns"].to_numpy() / 1e9, *(one[c].to_numpy() for c in "uvw")])
    scipy.io.savemat(tmp_path / "a.mat", {"acc": matrix, "axis": "x", "note": "bench 3"})
    scipy.io.savemat(tmp_path / "b.mat", {"data": matrix.T})
    meta = load_meta(None)
    a, _ = read_capture(tmp_path / "a.mat", None, meta, Limits())
    b, _ = read_capture(tmp_path / "b.mat", None, meta, Limits())
    assert np.array_equal(a["t_ns"].to_numpy(), one["t_ns"].to_numpy())
    assert np.array_equal(a.select("u", "v", "w").to_numpy(), one.select("u", "v", "w").to_numpy())
    assert a["axis"].cast(pl.String).unique().to_list() == ["x"] and b["axis"].null_count() == b.height
    assert_frame_equal(a.drop("axis", "label_source", "capture"), b.drop("axis", "label_source", "capture"))


def test_a_dataset_of_matlab_captures_runs_as_its_csv(tmp_path):
    """The whole run: the per-segment CSV files of a simulated dataset and
    the same samples as one MATLAB file each give the same tables."""
    csv = write_dataset(simulate(SPEC, 12), SPEC, tmp_path / "csv")
    mat = tmp_path / "mat"
    mat.mkdir()
    (mat / "dataset.toml").write_text((csv / "dataset.toml").read_text())
    for file in sorted(csv.glob("*.csv")):
        frame = pl.read_csv(file)
        scipy.io.savemat(mat / f"{file.stem}.mat", {c: frame[c].to_numpy()[None, :] for c in ("t", "u", "v", "w", "rate_hz", "angle_deg")}
                         | {"axis": np.array(frame["axis"].to_list())})
    assert load_dataset(mat).samples.height == load_dataset(csv).samples.height
    run_dataset(csv, tmp_path / "out_csv")
    run_dataset(mat, tmp_path / "out_mat")
    for name in ("fits", "intrinsic", "uncertainty_budget"):
        a, b = (pl.read_parquet(tmp_path / out / f"{name}.parquet").drop("dataset") for out in ("out_csv", "out_mat"))
        assert_frame_equal(a, b)  # exact


def _refused(path: Path, meta=None) -> str:
    with pytest.raises(InputError) as error:
        read_capture(path, None, meta or load_meta(None), Limits())
    message = str(error.value)
    assert "\n" not in message and str(path) in message
    return message


def test_what_is_refused(tmp_path, samples):
    m = as_matlab(samples)
    scipy.io.savemat(tmp_path / "short.mat", m | {"v": m["v"][:, :-1]})
    assert "variable 'v' holds" in _refused(tmp_path / "short.mat")
    scipy.io.savemat(tmp_path / "none.mat", {"x": np.arange(3.0)})
    assert "no variables u, v, w nor a matrix" in _refused(tmp_path / "none.mat")
    scipy.io.savemat(tmp_path / "two.mat", {"a": np.zeros((10, 3)), "b": np.zeros((10, 4))})
    assert "several matrices" in _refused(tmp_path / "two.mat")
    scipy.io.savemat(tmp_path / "untimed.mat", {c: m[c] for c in "uvw"})
    assert "no time" in _refused(tmp_path / "untimed.mat")
    scipy.io.savemat(tmp_path / "nan.mat", m | {"u": np.where(np.arange(m["u"].size) == 4, np.nan, m["u"])})
    assert "column 'u', row 5 is NaN" in _refused(tmp_path / "nan.mat")
    (tmp_path / "h5.mat").write_bytes(b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Dec  7 02:00:00 2026 HDF5 schema 1.00 ."
                                      .ljust(116) + bytes(8) + b"\x00\x02IM" + bytes(384))
    assert "v7.3" in _refused(tmp_path / "h5.mat")
    (tmp_path / "text.mat").write_text("t,u,v,w\n0,1,2,3\n")
    assert "cannot be read as a MATLAB file" in _refused(tmp_path / "text.mat")


def test_the_sample_rate_gives_the_time(tmp_path, samples):
    m = as_matlab(samples.head(500))
    scipy.io.savemat(tmp_path / "rated.mat", {c: m[c] for c in "uvw"})
    (tmp_path / "dataset.toml").write_text("[format]\nsample_rate_hz = 250.0\n")
    frame, _ = read_capture(tmp_path / "rated.mat", None, load_meta(tmp_path / "dataset.toml"), Limits())
    assert frame["t_ns"].to_list() == [k * 4_000_000 for k in range(500)]
