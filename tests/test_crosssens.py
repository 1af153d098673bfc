"""Cross-sensitivity matrices P and Q = P^-1 (Geist 2017 Eqs. 18 to 23) with
covariances, and the reverse (rotcal intrinsic --matrix) for interlaboratory
comparison."""

import json

import numpy as np
import polars as pl
import pytest

from rotcal.metrology.crosssens import cross_sensitivity, intrinsic_from_matrix, inverse_jacobian
from rotcal.model.physics import rotation_matrix
from rotcal.run import run_dataset

from testdata import REAL, REPO, truth_of


@pytest.fixture(scope="module")
def run(make_dataset, tmp_path_factory):
    ds = make_dataset(31)
    out = tmp_path_factory.mktemp("cs")
    return ds, out, run_dataset(ds, out)


def _matrix(frame, rate, name):
    part = frame.filter((pl.col("rate_hz") == rate) & (pl.col("matrix") == name))
    value = part["value"].to_numpy().reshape(3, 3)
    cov = np.array(part["cov"].to_list())
    return value, cov, part


def test_inverse_jacobian_matches_finite_differences():
    rng = np.random.default_rng(3)
    m = np.eye(3) * 1669 + rng.normal(0, 20, (3, 3))
    h = 1e-3
    numeric = np.column_stack([(np.linalg.inv(m + h * e.reshape(3, 3)) - np.linalg.inv(m - h * e.reshape(3, 3))).ravel() / (2 * h)
                               for e in np.eye(9)])
    np.testing.assert_allclose(inverse_jacobian(m), numeric, rtol=1e-6, atol=1e-7 * np.abs(numeric).max())


def test_table_has_p_and_q_for_every_rate_and_p_inverts_the_true_responsivity(run):
    ds, out, outcome = run
    frame = pl.read_parquet(out / "cross_sensitivity.parquet")
    assert sorted(set(frame["rate_hz"])) == [0.0, 0.01, 0.05, 0.1, 0.5]
    assert frame.height == 5 * 2 * 9 and set(frame["frame"]) == {"table"}
    truth = np.array(truth_of(ds)["dut"]["responsivity"])
    for res in outcome.results:
        P, cov_P, part = _matrix(frame, res.rate_hz, "P")
        Q, _, _ = _matrix(frame, res.rate_hz, "Q")
        np.testing.assert_allclose(P @ Q, np.eye(3), atol=1e-12)
        z = (P - np.linalg.inv(truth)) / np.sqrt(np.diag(cov_P)).reshape(3, 3)
        assert np.abs(z).max() < 4.5
        assert part["unit"][0] == "(m/s^2)/bit" and part.filter(pl.col("row") == "x")["column"].to_list() == ["u", "v", "w"]


def test_p_round_trips_to_the_same_intrinsic_parameters_and_uncertainties(run):
    """The six sensitivity and angle parameters of P, with P's full
    covariance, equal the run's (first-order propagation through Q = P^-1
    and back is exact: the two Jacobians are inverse)."""
    _, out, outcome = run
    frame = pl.read_parquet(out / "cross_sensitivity.parquet")
    for res in outcome.results:
        P, cov_P, _ = _matrix(frame, res.rate_hz, "P")
        value, cov = intrinsic_from_matrix(P, cov_P)
        np.testing.assert_allclose(value, res.value[:6], rtol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(cov)), res.std_uncertainty[:6], rtol=1e-8)


def test_a_rotated_mount_gives_the_same_intrinsic_parameters(run):
    """Another lab's mount: Q' = Q M^T, P' = M P. The intrinsic parameters
    and their uncertainties do not change (Geist section 6)."""
    _, _, outcome = run
    res = outcome.results[0]
    cs = cross_sensitivity(res, 3e-5)
    M = rotation_matrix([0.3, -1.0, 0.4], 23.0)
    lift = np.kron(M, np.eye(3))  # vec(M P) = (M x I) vec(P), row-major
    v0, c0 = intrinsic_from_matrix(cs.P, cs.cov_P)
    v1, c1 = intrinsic_from_matrix(M @ cs.P, lift @ cs.cov_P @ lift.T)
    np.testing.assert_allclose(v1, v0, rtol=1e-12)
    np.testing.assert_allclose(c1, c0, rtol=1e-8, atol=1e-14 * np.abs(c0).max())


def _write_matrix_csv(path, P, u=None, header=True):
    lines = [",u,v,w"] if header else []
    lines += [f"{r}," + ",".join(f"{x:.17g}" for x in row) for r, row in zip("xyz", P)]
    if u is not None:
        lines += [f"{r}," + ",".join(f"{x:.17g}" for x in row) for r, row in zip("xyz", u)]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_cli_reads_the_contract_csv_and_matches_the_run(cli, run, tmp_path):
    """rotcal intrinsic --matrix on the run's P and its standard
    uncertainties (the contract's file, which carries no correlations): the
    values equal the run's; the uncertainties are those of independent
    elements, which a Monte Carlo draw of independent elements confirms."""
    _, out, outcome = run
    frame = pl.read_parquet(out / "cross_sensitivity.parquet")
    P, cov_P, _ = _matrix(frame, 0.0, "P")
    u = np.sqrt(np.diag(cov_P)).reshape(3, 3)
    path = _write_matrix_csv(tmp_path / "lab_b.csv", P, u)
    status, stdout, stderr = cli("intrinsic", "--matrix", path, "--out", tmp_path, "--unit", "bit")
    assert status == 0, stderr
    assert "phi_uv" in stdout and "±" in stdout
    got = pl.read_parquet(tmp_path / "lab_b_intrinsic.parquet")
    assert got["parameter"].to_list() == ["s_u", "s_v", "s_w", "phi_uv", "phi_vw", "phi_wu"]
    np.testing.assert_allclose(got["value"].to_numpy(), outcome.results[0].value[:6], rtol=1e-12)
    rng = np.random.default_rng(5)
    draws = np.array([intrinsic_from_matrix(P + rng.standard_normal((3, 3)) * u, np.zeros((9, 9)))[0] for _ in range(2000)])
    np.testing.assert_allclose(got["std_uncertainty"].to_numpy(), draws.std(axis=0), rtol=0.08)
    assert got["unit"][0] == "bit/(m/s^2)"


def test_cli_without_uncertainties_and_without_labels(cli, tmp_path):
    P = np.linalg.inv(np.diag([1669.0, 1670.0, 1668.0]) @ rotation_matrix([1.0, 2.0, 3.0], 5.0))
    status, stdout, _ = cli("intrinsic", "--matrix", _write_matrix_csv(tmp_path / "p.csv", P, header=False), "--out", tmp_path)
    assert status == 0
    got = pl.read_parquet(tmp_path / "p_intrinsic.parquet")
    np.testing.assert_allclose(got["value"].to_numpy(), [1669.0, 1670.0, 1668.0, 90.0, 90.0, 90.0], rtol=1e-12)
    assert got["std_uncertainty"].is_null().all()


@pytest.mark.real
def test_imucal_matrix_gives_the_intrinsic_parameters_of_its_calibration(cli, tmp_path):
    """imucal's K_a R_a is the responsivity matrix in the case frame:
    P = (K_a R_a)^-1, and its intrinsic parameters are rotcal's
    12-parameter fit of the same session's labelled poses taken as exact
    references (the matrices agree to 1e-15)."""
    from rotcal.combine.poses import labelled_poses, reference_fit
    from rotcal.ingest.dataset import load_dataset
    from rotcal.segment import segment_by_labels

    ref = json.loads((REAL / "imucal_session" / "annotated_session_reference_cal.json").read_text())
    P = np.linalg.inv(np.array(ref["K_a"]) @ np.array(ref["R_a"]))
    status, _, _ = cli("intrinsic", "--matrix", _write_matrix_csv(tmp_path / "imucal.csv", P), "--out", tmp_path)
    assert status == 0
    ds = load_dataset(REAL / "imucal_session", REPO / "configs" / "imucal_session.toml")
    fit = reference_fit(labelled_poses(*segment_by_labels(ds.samples, ds.name)), ds.meta.g_local, 0.0)
    ours = fit.result.value[:6]
    np.testing.assert_allclose(pl.read_parquet(tmp_path / "imucal_intrinsic.parquet")["value"].to_numpy(), ours, rtol=1e-12)


@pytest.mark.parametrize("text, problem", [
    (",u,v,w\nx,1,0,0\ny,0,1,0\n", "expected 3 rows"),
    ("x,1,0,0\ny,0,1,zero\nz,0,0,1\n", "line 2: expected three numbers"),
    ("x,1,0\ny,0,1\nz,0,0\n", "line 1: expected three numbers"),
    ("1,0,0,0,0\n0,1,0\n0,0,1\n", "line 1: expected three numbers"),
    ("x,1,0,0\nz,0,1,0\ny,0,0,1\n", "rows must be x, y, z"),
    ("x,1,2,3\ny,2,4,6\nz,0,0,1\n", "singular"),
    ("x,1,0,0\ny,0,1,0\nz,0,0,1\nx,0.1,0,0\ny,0,-0.1,0\nz,0,0,0.1\n", "must not be negative"),
])
def test_bad_matrix_files_give_a_one_line_message(cli, tmp_path, text, problem):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    status, _, stderr = cli("intrinsic", "--matrix", path, "--out", tmp_path)
    assert status == 2 and problem in stderr and "bad.csv" in stderr and "Traceback" not in stderr
