"""``rotcal apply``: the correction a = P (R - O) against an independent
solve with Q, the per-sample covariance against the Jacobian written out,
|a| = g_local on the static dwells of a simulated recording and on the real
Xsens poses, the three file forms agreeing, and bad input refused in one line."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from rotcal.apply import correct, correction_covariance
from rotcal.ingest.dataset import load_dataset
from rotcal.model.calibration import Calibration
from rotcal.run import RunOutcome, run_dataset

from testdata import REAL, REPO, truth_of

XSENS = REAL / "imu_tk_xsens"


def calibrate(dataset, out, meta=None) -> tuple[Path, RunOutcome]:
    """A run of ``dataset`` into ``out``: the calibration.json it wrote, and its outcome."""
    return out / "calibration.json", run_dataset(dataset, out, meta)


@pytest.fixture(scope="module")
def simulated(make_dataset, tmp_path_factory):
    """A clean simulated recording and its calibration.json."""
    data = make_dataset(11)
    cal, _ = calibrate(data, tmp_path_factory.mktemp("apply_cal"))
    return data, cal


def test_correction_is_the_inverse_of_the_responsivity_model():
    # R = O + Q a (docs/conventions.md): solving with Q must give back a
    rng = np.random.default_rng(3)
    Q = np.eye(3) * 1670 + rng.normal(0, 20, (3, 3))
    O = np.array([-240.0, 17.0, 226.0])  # noqa: E741
    a = rng.normal(0, 9.8, (3, 1000))
    raw = O[:, None] + Q @ a
    np.testing.assert_allclose(correct(raw, np.linalg.inv(Q), O), a, rtol=0, atol=1e-12)


def test_sample_covariance_against_the_jacobian_written_out(simulated):
    _, path = simulated
    rng = np.random.default_rng(5)
    # a covariance with every correlation (a table run's P and O are nearly uncorrelated)
    half = rng.normal(0, 1e-4, (12, 12))
    rc = replace(Calibration.read(path).rate(None), correction_cov=half @ half.T)
    raw = rng.normal(0, 16000, (3, 7))
    cov = correction_covariance(raw, rc)
    pairs = [(0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)]
    for n in range(raw.shape[1]):
        J = np.zeros((3, 12))
        for i in range(3):
            J[i, 3 * i : 3 * i + 3] = raw[:, n] - rc.O_vector  # da_i/dP_ij
            J[i, 9:] = -rc.P_matrix[i]                          # da_i/dO_j
        expected = J @ rc.correction_cov @ J.T
        np.testing.assert_allclose(cov[:, n], [expected[i, k] for i, k in pairs], rtol=1e-9)


def _dwell_norms(samples: pl.DataFrame, calibrated: pl.DataFrame) -> np.ndarray:
    """|mean a| of each static dwell (one table angle of a static segment):
    the mean first, so that the noise does not bias |a|."""
    both = pl.concat([samples.select("capture", "rate_hz", "angle_deg"), calibrated], how="horizontal")
    dwells = both.filter(pl.col("rate_hz") == 0).group_by("capture", "angle_deg").agg(pl.col("a_x", "a_y", "a_z").mean())
    return np.linalg.norm(dwells.select("a_x", "a_y", "a_z").to_numpy(), axis=1)


def test_static_dwells_of_a_simulated_recording_read_g_local(simulated, tmp_path, cli):
    data, cal = simulated
    out = tmp_path / "a.parquet"
    code, stdout, stderr = cli("apply", cal.parent, data, "--out", out, "--uncertainty")
    assert code == 0, stderr
    calibrated = pl.read_parquet(out)
    samples = load_dataset(data).samples
    assert calibrated.height == samples.height and "54,000 samples calibrated (0 Hz, frame table)" in stdout
    np.testing.assert_array_equal(calibrated["t_ns"].to_numpy(), samples["t_ns"].to_numpy())
    norms = _dwell_norms(samples, calibrated)
    g = truth_of(data)["g_local"]
    assert norms.size == 72 and abs(norms.mean() / g - 1) < 2e-5
    meta = pq.read_schema(out).metadata
    assert meta[b"rotcal.frame"] == b"table" and meta[b"rotcal.calibration_rate_hz"] == b"0.0"
    # the uncertainty column is the calibration's covariance propagated to these samples
    raw = np.stack([samples[c].cast(float).to_numpy() for c in "uvw"])
    u = np.sqrt(correction_covariance(raw[:, :5], Calibration.read(cal).rate(None))[[0, 3, 5]])
    np.testing.assert_allclose(calibrated.select("u_a_x", "u_a_y", "u_a_z").head(5).to_numpy().T, u, rtol=1e-12)
    assert 1e-5 < calibrated["u_a_z"].median() < 1e-3  # m/s^2: the order of the calibration's own uncertainty


def test_csv_and_mcap_hold_what_parquet_holds(simulated, tmp_path, cli):
    data, cal = simulated
    for suffix in ("parquet", "csv", "mcap"):
        code, _, stderr = cli("apply", cal, data, "--out", tmp_path / f"a.{suffix}", "--uncertainty", "--rate", "0.5")
        assert code == 0, stderr
    ref = pl.read_parquet(tmp_path / "a.parquet")
    csv = pl.read_csv(tmp_path / "a.csv", comment_prefix="#", schema_overrides={"t": pl.String})
    assert csv.columns == ["t", "a_x", "a_y", "a_z", "u_a_x", "u_a_y", "u_a_z"]
    for col in csv.columns[1:]:
        np.testing.assert_array_equal(csv[col].to_numpy(), ref[col].to_numpy())  # shortest round-trip text
    sec_ns = csv["t"].str.split_exact(".", 1).struct.unnest()
    t_ns = sec_ns["field_0"].cast(pl.Int64) * 1_000_000_000 + sec_ns["field_1"].cast(pl.Int64)
    np.testing.assert_array_equal(t_ns.to_numpy(), ref["t_ns"].to_numpy())
    assert "# frame: table" in (tmp_path / "a.csv").read_text()[:500]
    with (tmp_path / "a.mcap").open("rb") as fh:
        decoded = make_reader(fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()
        messages = [(channel, msg) for _, (_, channel, _, msg) in zip(range(3), decoded)]
    cov = correction_covariance(np.stack([load_dataset(data).samples[c].cast(float).to_numpy()[:3] for c in "uvw"]),
                                Calibration.read(cal).rate(0.5))
    for k, (channel, msg) in enumerate(messages):
        assert channel.topic == "/imu/calibrated" and msg.header.frame_id == "table"
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == ref["t_ns"][k]
        lin = msg.linear_acceleration
        assert [lin.x, lin.y, lin.z] == [ref["a_x"][k], ref["a_y"][k], ref["a_z"][k]]
        full = np.array(msg.linear_acceleration_covariance).reshape(3, 3)
        np.testing.assert_array_equal(full, full.T)
        np.testing.assert_allclose(np.diag(full), cov[[0, 3, 5], k], rtol=1e-15)
        assert full[0, 2] == cov[2, k]
        assert msg.orientation_covariance[0] == -1 and msg.angular_velocity_covariance[0] == -1


def test_bad_calibration_recording_or_output_is_one_line(simulated, tmp_path, cli):
    data, cal = simulated
    (tmp_path / "broken.json").write_text('{"schema": "calibration"')
    mismatched = tmp_path / "count.toml"
    mismatched.write_text((data / "dataset.toml").read_text().replace('output_unit = "bit"', 'output_unit = "count"'))
    cases = [
        (("apply", tmp_path / "broken.json", data, "--out", tmp_path / "x.csv"), "cannot read calibration"),
        (("apply", tmp_path / "none", data, "--out", tmp_path / "x.csv"), "cannot read calibration"),
        (("apply", cal, tmp_path / "missing", "--out", tmp_path / "x.csv"), "dataset not found"),
        (("apply", cal, data, "--out", tmp_path / "x.txt"), "cannot tell the output format"),
        (("apply", cal, data, "--out", tmp_path / "no" / "x.csv"), "does not exist"),
        (("apply", cal, data, "--out", tmp_path), "cannot tell the output format"),
        (("apply", cal, data, "--out", tmp_path / "x.csv", "--rate", "2"), "no rate 2 Hz"),
        (("apply", cal, data, "--out", tmp_path / "x.csv", "--meta", mismatched), "output unit is 'count'"),
    ]
    for args, message in cases:
        code, _, stderr = cli(*args)
        assert code == 2 and message in stderr and stderr.count("\n") == 1, (args, stderr)
    assert not list(tmp_path.glob("x.*")) and not list(tmp_path.glob(".x.*"))


@pytest.mark.real
def test_xsens_static_poses_read_g_local(tmp_path):
    meta = REPO / "configs" / "imu_tk_xsens.toml"
    cal, outcome = calibrate(XSENS, tmp_path / "cal", meta)
    from rotcal.apply import apply_calibration

    done = apply_calibration(cal, XSENS, tmp_path / "x.parquet", meta=meta)
    assert done.frame == "intrinsic" and done.samples == 51175
    calibrated = pl.read_parquet(tmp_path / "x.parquet")
    poses = outcome.static.check
    g = json.loads(cal.read_text())["g_local"]["value"]
    errors = []
    for start, end in poses.select("t_start_ns", "t_end_ns").iter_rows():
        a = calibrated.filter(pl.col("t_ns").is_between(start, end)).select("a_x", "a_y", "a_z").mean().to_numpy()[0]
        errors.append(np.linalg.norm(a) / g - 1)
    rms = float(np.sqrt(np.mean(np.square(errors))))
    assert len(errors) == 38 and rms <= 1.5e-4
    # the run's own |a| check of the same poses: the same numbers
    np.testing.assert_allclose(rms, np.sqrt(np.mean(poses["deviation_rel"].to_numpy() ** 2)), rtol=1e-9)
