"""``rotcal run`` on recordings with static poses and no table segments:
the two real recordings read in place, and simulated hand-placed and jig
recordings with known truth."""

import numpy as np
import polars as pl
import pytest

from rotcal.run import run_dataset
from rotcal.tables import schema

from posesim import G_LOCAL, hand_placed, samples_frame
from testdata import REAL, REPO

# Xsens factory calibration (PROVENANCE.txt): counts per m/s^2 and counts
XSENS_SCALE = np.array([415.0, 413.0, 415.0])
XSENS_OFFSET = np.array([33123.0, 33276.0, 32360.0])


@pytest.fixture(scope="module")
def xsens(tmp_path_factory):
    out = tmp_path_factory.mktemp("xsens")
    outcome = run_dataset(REAL / "imu_tk_xsens", out, REPO / "configs" / "imu_tk_xsens.toml")
    return outcome, pl.read_parquet(out / "poses.parquet"), out


@pytest.mark.real
def test_xsens_orientation_free_matches_the_factory_calibration(xsens):
    """Fitted on all still intervals: sensitivities within 0.5 % and offsets
    within 10 counts of the Xsens factory calibration."""
    outcome, poses, out = xsens
    assert outcome.static.method == "orientation-free" and outcome.static.frame == "intrinsic"
    assert 36 <= poses.height <= 40 and set(poses["source"]) == {"stillness"}
    value = outcome.results[0].value
    print(f"s {value[:3]}, O {value[6:]}")
    assert np.all(np.abs(value[:3] / XSENS_SCALE - 1) < 0.005)
    assert np.all(np.abs(value[6:] - XSENS_OFFSET) < 10)
    intrinsic = pl.read_parquet(out / "intrinsic.parquet")
    assert intrinsic.height == 18 and set(intrinsic["rate_hz"]) == {0.0}
    assert intrinsic["model"].to_list() == ["baseline"] * 9 + ["orthogonal"] * 9
    # the F test rejects orthogonal axes (phi_vw is 88.8 degrees): the nine parameters are chosen
    assert any(n.startswith("static model: baseline: the F test of orthogonal axes") and "rejects" in n for n in outcome.notes)
    assert set(pl.read_parquet(out / "cross_sensitivity.parquet")["frame"]) == {"intrinsic"}


@pytest.mark.real
def test_xsens_every_other_pose_held_out(xsens):
    """Fitted on every other still interval (the even ones, the initial rest
    first), the poses left out have |a| within 0.1 % of g_local. The odd
    half has no pose with +x up, so its fit extrapolates there: its
    predictions miss the even poses by up to 0.3 %, within their stated
    uncertainty."""
    outcome, poses, _ = xsens
    g = outcome.results[0].g_local
    odd = poses.filter(pl.col("fold") == 1)
    assert np.abs(odd["norm_held_out_m_s2"].to_numpy() / g - 1).max() < 1e-3
    even = poses.filter(pl.col("fold") == 0)
    z = (even["norm_held_out_m_s2"] - g) / even["u_norm_held_out_m_s2"]
    assert np.abs(z.to_numpy()).max() < 3.0
    assert np.abs(poses["deviation_rel"].to_numpy()).max() < 3e-4


@pytest.mark.real
def test_xsens_run_prints_parameters_and_the_magnitude_check(cli, tmp_path):
    status, stdout, stderr = cli("run", REAL / "imu_tk_xsens", "--meta", REPO / "configs" / "imu_tk_xsens.toml",
                                 "--out", tmp_path)
    assert status == 0, stderr
    assert "s_u" in stdout and "±" in stdout and "orientation-free fit" in stdout
    assert "|a| check" in stdout and "held out: odd positions, fit to the even" in stdout
    assert "poses.parquet" in stdout


@pytest.mark.real
def test_imucal_run_prints_the_six_face_fit_and_every_pose(cli, tmp_path):
    status, stdout, stderr = cli("run", REAL / "imucal_session", "--meta", REPO / "configs" / "imucal_session.toml",
                                 "--out", tmp_path)
    assert status == 0, stderr
    assert "orientation-free fit (|a| = g_local) to 6 labelled poses" in stdout and "residual dof 0" in stdout
    assert "exactly determined" in stdout and "nan" not in stdout
    for label in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a"):
        assert label in stdout
    poses = pl.read_parquet(tmp_path / "poses.parquet")
    assert poses.columns == list(schema("poses").columns)
    assert poses["label"].to_list() == ["x_a", "x_p", "y_a", "y_p", "z_a", "z_p"]
    np.testing.assert_allclose(poses.select("ref_x", "ref_y", "ref_z").to_numpy(),
                               [[-1, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0], [0, 0, -1], [0, 0, 1]])
    correction = pl.read_parquet(tmp_path / "correction.parquet")
    assert correction.height == 6 and set(correction["input_unit"]) == {"count"}
    dof = pl.read_parquet(tmp_path / "correction_uncertainty.parquet").group_by("parameters").agg(pl.col("dof").first())
    assert dict(dof.iter_rows()) == {6: 4, 12: 2}  # the six faces do not determine the cubic term (x^3 = x on -1, 0, +1 g)
    assert "AN4399 15-parameter correction skipped: the positions do not determine gamma" in " ".join(stderr.split())


def _write(tmp_path, frame, g_local=G_LOCAL):
    tmp_path.mkdir(parents=True, exist_ok=True)
    frame.write_csv(tmp_path / "session.csv")
    (tmp_path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {g_local}\n'
                                           "g_local_uncertainty = 0.0\n")
    return tmp_path


def test_simulated_hand_placed_recording_end_to_end(tmp_path):
    """24 poses of random orientation, 3 s each, joined by 1.5 s turns: the
    stillness detector finds them, and the nine parameters match the truth
    within their uncertainties."""
    sim = hand_placed(77, n_poses=24, samples=300, move_samples=150)
    data = _write(tmp_path / "data", samples_frame(sim))
    outcome = run_dataset(data, tmp_path / "out")
    poses = pl.read_parquet(tmp_path / "out" / "poses.parquet")
    assert poses.height == 24
    z = (outcome.results[0].value - sim.truth) / outcome.results[0].std_uncertainty
    assert np.abs(z).max() < 4, z


def test_simulated_jig_recording_gives_intrinsic_parameters_and_corrections(tmp_path):
    """Eight jig positions given as gx, gy, gz (in g): the 12-parameter
    reference fit gives the truth within its uncertainty; the AN4399
    correction is written with the jig's frame."""
    directions = np.vstack([np.eye(3), -np.eye(3), [[1, 1, 1], [-1, 1, -1]] / np.sqrt(3)])
    sim = hand_placed(78, samples=200, directions=directions)
    ref = directions[sim.pose]
    frame = samples_frame(sim).with_columns(gx=ref[:, 0], gy=ref[:, 1], gz=ref[:, 2])
    outcome = run_dataset(_write(tmp_path / "data", frame), tmp_path / "out")
    assert outcome.static.frame == "jig" and outcome.static.fit.dof == 3 * (8 - 4)
    z = (outcome.results[0].value - sim.truth) / outcome.results[0].std_uncertainty
    assert np.abs(z).max() < 4, z
    w = np.linalg.inv(G_LOCAL * sim.responsivity)
    twelve = pl.read_parquet(tmp_path / "out" / "correction.parquet").filter(pl.col("parameters") == 12).sort("channel")
    np.testing.assert_allclose(twelve.select("W_x", "W_y", "W_z").to_numpy(), w, rtol=2e-3, atol=2e-3 * np.abs(w).max())


def test_eight_poses_give_the_orthogonal_model(cli, tmp_path):
    """Eight poses cannot determine nine parameters with a residual degree
    of freedom, but they determine the six of orthogonal axes: those are the
    result (rows model = orthogonal), with the reason the nine are not."""
    sim = hand_placed(79, n_poses=8, samples=300, move_samples=150)
    data = _write(tmp_path / "data", samples_frame(sim))
    status, _, stderr = cli("run", data, "--out", tmp_path / "out")
    assert status == 0, stderr
    assert "static model: orthogonal: the baseline model is not determined: 8 static poses" in " ".join(stderr.split())
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet")
    assert set(intrinsic["model"]) == {"orthogonal"} and intrinsic.height == 9
    assert intrinsic.filter(pl.col("parameter").str.starts_with("phi"))["value"].to_list() == [90.0] * 3


def test_too_few_poses_are_refused_with_the_pose_table(cli, tmp_path):
    """Five poses do not determine even the six parameters: exit 3 with the
    reason, and poses.parquet still lists the five intervals found."""
    sim = hand_placed(79, n_poses=5, samples=300, move_samples=150)
    data = _write(tmp_path / "data", samples_frame(sim))
    status, _, stderr = cli("run", data, "--out", tmp_path / "out")
    assert status == 3
    assert ("no table segments, and the static poses cannot be reduced: orthogonal axes (six parameters): 5 static "
            "poses: the 6-parameter model needs at least 6 (its 6 intrinsic parameters); nine parameters: 5 static "
            "poses: the 9-parameter model needs at least 10") in " ".join(stderr.split())
    poses = pl.read_parquet(tmp_path / "out" / "poses.parquet")
    assert poses.height == 5 and poses["norm_m_s2"].is_null().all() and poses["determines"].is_null().all()
    np.testing.assert_allclose(poses["n_samples"].to_numpy(), 300, atol=30)


def test_jig_positions_at_two_temperatures_give_corrections_per_temperature(tmp_path):
    """The same eight jig positions at 20 and 60 degC (temperature_c): one
    set of corrections per temperature, and the AN4399 section 9 line
    through them."""
    directions = np.vstack([np.eye(3), -np.eye(3), [[1, 1, 1], [-1, 1, -1]] / np.sqrt(3)])
    frames = []
    for k, t_c in enumerate((20.0, 60.0)):
        sim = hand_placed(80, samples=100, directions=directions)
        ref = directions[sim.pose]
        frames.append(samples_frame(sim).with_columns(
            t=pl.col("t") + 100.0 * k, gx=ref[:, 0], gy=ref[:, 1], gz=ref[:, 2],
            temperature_c=t_c + 0.1 * np.sin(np.arange(len(ref)))))
    run_dataset(_write(tmp_path / "data", pl.concat(frames)), tmp_path / "out")
    correction = pl.read_parquet(tmp_path / "out" / "correction.parquet")
    assert sorted(set(np.round(correction["temperature_c"].to_numpy(), 1))) == [20.0, 60.0]
    assert correction.height == 2 * 9
    line = pl.read_parquet(tmp_path / "out" / "correction_temperature.parquet")
    assert set(line["n_temperatures"]) == {2} and (line["gamma_t"] == 0).all()
    w20 = correction.filter((pl.col("parameters") == 12) & (pl.col("temperature_c") < 40)).sort("channel")["W_x"].to_numpy()
    fitted = line.filter((pl.col("parameters") == 12) & (pl.col("coefficient") == "W_x")).sort("channel")
    t20 = correction.filter(pl.col("temperature_c") < 40)["temperature_c"][0]
    np.testing.assert_allclose(fitted["alpha"].to_numpy() + fitted["beta"].to_numpy() * t20, w20, rtol=1e-9)
