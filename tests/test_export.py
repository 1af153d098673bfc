"""``rotcal export``: every form read back by a small parser of its own and
turned into calibrated accelerations with that stack's documented
convention (docs/apply.md), checked against a = P (R - O) for the parts the
form holds, and the size the warning gives to what it drops checked by sampling."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml
from scipy.linalg import polar

from rotcal.apply import export_calibration
from rotcal.model.calibration import Calibration, rate_calibration
from rotcal.model.results import BudgetInput, IntrinsicResult

G = 9.80665
C = 1 / 1670  # the driver's nominal m/s^2 per bit (the test DUTs give about 1670 bit per m/s^2)


def _calibration(Q: np.ndarray, O: np.ndarray, unit: str = "bit") -> Calibration:  # noqa: E741
    """A calibration whose responsivity matrix is Q (output unit per m/s^2) and offsets O."""
    state = np.concatenate([Q.ravel() * G, O])
    cov = np.diag(np.concatenate([np.full(9, 0.5), np.full(3, 4.0)]))
    res = IntrinsicResult.from_state(0.0, state, cov, G, 1e-5, [(BudgetInput("seg1", "segment", 1, "x", 30), cov)])
    rc = rate_calibration(res, "table", "baseline", "test", unit)
    return Calibration("dut", {}, unit, G, 1e-5, "test", (), {}, "0", "2026-11-24T00:00:00Z", (rc,))


def _skewed() -> Calibration:
    """A DUT mounted at an angle, with non-orthogonal axes (a few mrad)."""
    rng = np.random.default_rng(2)
    rotation = polar(np.eye(3) + rng.normal(0, 0.05, (3, 3)))[0]
    directions = np.eye(3) + np.array([[0, 0, 0], [2e-3, 0, 0], [-1e-3, 3e-3, 0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    s = np.array([1660.0, 1675.0, 1690.0])
    return _calibration(s[:, None] * directions @ rotation.T, np.array([-240.0, 17.0, 226.0]))


def _orthogonal() -> Calibration:
    """Axes orthogonal and along the frame: the per-axis forms hold it all."""
    return _calibration(np.diag([1660.0, 1675.0, 1690.0]), np.array([-240.0, 17.0, 226.0]))


def _raw(n: int = 200) -> np.ndarray:
    return np.random.default_rng(9).uniform(-16000, 16000, (3, n))


def read_ardupilot(text: str) -> dict[str, float]:
    """A Mission Planner .param file: NAME,VALUE lines, # comments."""
    return {name: float(value) for name, value in
            (line.split(",") for line in text.splitlines() if line and not line.startswith("#"))}


def read_qgc(text: str) -> dict[str, float]:
    """A QGroundControl parameter file: vehicle, component, name, value, type (tab-separated), # comments."""
    rows = [line.split("\t") for line in text.splitlines() if line and not line.startswith("#")]
    assert all(len(r) == 5 and r[:2] == ["1", "1"] and r[4] == "9" for r in rows)
    return {r[2]: float(r[3]) for r in rows}


def _stack_reading(offset: np.ndarray, scale: np.ndarray, raw: np.ndarray) -> np.ndarray:
    """ArduPilot and PX4: a = (raw_m_s2 - offset) * scale per axis, raw_m_s2 = C R from the driver."""
    return scale[:, None] * (C * raw - offset[:, None])


@pytest.mark.parametrize("fmt", ["ardupilot", "px4"])
def test_flight_stack_files_give_each_axis_its_own_sensitivity(fmt):
    read, prefix, off, sc = ((read_ardupilot, "INS_", "ACCOFFS_{}", "ACCSCAL_{}") if fmt == "ardupilot"
                             else (read_qgc, "CAL_ACC0_", "{}OFF", "{}SCALE"))
    raw = _raw()
    for cal in (_orthogonal(), _skewed()):
        params = read(export_calibration(cal, fmt, nominal_scale=C).text)
        assert len(params) == 6
        offset = np.array([params[prefix + off.format(x)] for x in "XYZ"])
        scale = np.array([params[prefix + sc.format(x)] for x in "XYZ"])
        rc = cal.rate(None)
        Q = np.linalg.inv(rc.P_matrix)
        s = np.linalg.norm(Q, axis=1)  # each channel's sensitivity, whatever the frame
        expected = (raw - rc.O_vector[:, None]) / s[:, None]
        np.testing.assert_allclose(_stack_reading(offset, scale, raw), expected, rtol=2e-8, atol=2e-8 * G)
    # orthogonal axes along the frame: the whole correction
    rc = _orthogonal().rate(None)
    params = read(export_calibration(_orthogonal(), fmt, nominal_scale=C).text)
    offset = np.array([params[prefix + off.format(x)] for x in "XYZ"])
    scale = np.array([params[prefix + sc.format(x)] for x in "XYZ"])
    np.testing.assert_allclose(_stack_reading(offset, scale, raw), rc.P_matrix @ (raw - rc.O_vector[:, None]),
                               rtol=2e-8, atol=2e-8 * G)


def test_warning_states_the_size_of_the_dropped_non_orthogonality():
    cal = _skewed()
    export = export_calibration(cal, "ardupilot", nominal_scale=C)
    assert len(export.warnings) == 1 and "non-orthogonality" in export.warnings[0]
    stated = float(export.warnings[0].split("up to ")[1].split(" mg")[0])
    # per-axis model reads N a; the nearest orthogonal axes U a: the worst error over |a| = 1 g, sampled
    Q = np.linalg.inv(cal.rate(None).P_matrix)
    N = Q / np.linalg.norm(Q, axis=1, keepdims=True)
    U = polar(N)[0]
    a = np.random.default_rng(1).normal(size=(3, 200_000))
    a /= np.linalg.norm(a, axis=0)
    worst_mg = 1000 * np.linalg.norm((N - U) @ a, axis=0).max()
    assert stated == pytest.approx(worst_mg, rel=2e-3)
    assert 1.0 < stated < 3.0  # mrad-sized angles: about a milli-g
    assert "up to 0 mg" in export_calibration(_orthogonal(), "px4", nominal_scale=C).warnings[0]


def test_yaml_holds_the_whole_correction_in_imu_tks_convention():
    cal = _skewed()
    doc = yaml.safe_load(export_calibration(cal, "yaml").text)
    T, K, B = (np.array(doc[k], float) for k in ("T", "K", "B"))
    raw, rc = _raw(), cal.rate(None)
    np.testing.assert_allclose(T @ K @ (raw - B[:, None]), rc.P_matrix @ (raw - rc.O_vector[:, None]), rtol=1e-13,
                               atol=1e-13 * G)
    mis = doc["misalignment"]
    imu_tk_T = [[1, -mis["mis_yz"], mis["mis_zy"]], [mis["mis_xz"], 1, -mis["mis_zx"]],
                [-mis["mis_xy"], mis["mis_yx"], 1]]
    np.testing.assert_array_equal(T, imu_tk_T)
    assert np.count_nonzero(K - np.diag(np.diag(K))) == 0
    assert (doc["frame"], doc["raw_unit"], doc["calibrated_unit"]) == ("table", "bit", "m/s^2")


def test_json_holds_the_correction_and_its_uncertainty():
    cal = _skewed()
    doc = json.loads(export_calibration(cal, "json").text)
    rc, raw = cal.rate(None), _raw()
    P, O = np.array(doc["P"]), np.array(doc["O"])  # noqa: E741
    np.testing.assert_array_equal(P @ (raw - O[:, None]), rc.P_matrix @ (raw - rc.O_vector[:, None]))
    cov = np.array(doc["covariance"]["matrix"])
    np.testing.assert_allclose(np.array(doc["u_P"]).ravel(), np.sqrt(np.diag(cov)[:9]), rtol=1e-15)
    np.testing.assert_allclose(doc["u_O"], np.sqrt(np.diag(cov)[9:]), rtol=1e-15)
    assert export_calibration(cal, "json").warnings == ()


def test_units_and_ranges(tmp_path, cli):
    path = _skewed().write(tmp_path / "calibration.json")
    code, _, stderr = cli("export", path, "--format", "ardupilot")
    assert code == 2 and "--nominal-scale" in stderr and stderr.count("\n") == 1
    for args in (("--format", "betaflight"), ("--format", "px4", "--nominal-scale", "-1")):
        code, _, stderr = cli("export", path, *args)
        assert code == 2 and stderr.count("\n") == 1, stderr
    # a nominal scale far from the DUT's: scale 0.6, outside ArduPilot's 0.8 to 1.2
    code, stdout, stderr = cli("export", path, "--format", "ardupilot", "--nominal-scale", "0.01")
    assert code == 0 and "outside ArduPilot's ranges" in stderr
    code, stdout, stderr = cli("export", path, "--format", "px4", "--nominal-scale", str(C), "--out", tmp_path / "a.params")
    assert code == 0 and "non-orthogonality" in stderr
    assert read_qgc((tmp_path / "a.params").read_text())["CAL_ACC0_ZSCALE"] == pytest.approx(1670 / 1690, rel=1e-6)
    # output already in m/s^2: no driver scale involved
    ms2 = _calibration(np.eye(3) * 1.02, np.array([0.1, -0.2, 0.3]), "m/s^2")
    params = read_ardupilot(export_calibration(ms2, "ardupilot").text)
    assert params["INS_ACCSCAL_X"] == pytest.approx(1 / 1.02, rel=1e-8) and params["INS_ACCOFFS_Z"] == pytest.approx(0.3)
