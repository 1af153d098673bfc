"""calibration.json's document (rotcal.model.calibration): P = Q^-1 and
its covariance against finite differences, effective dof by hand
(Welch-Satterthwaite, GUM G.2b), the schema's round trip and its refusals."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rotcal.errors import InputError
from rotcal.model.calibration import Calibration, rate_calibration
from rotcal.model.results import BudgetInput, IntrinsicResult, intrinsic_jacobian

G, U_G = 9.80665, 2e-4


def _result() -> IntrinsicResult:
    rng = np.random.default_rng(7)
    q = np.eye(3) * 1000 + rng.normal(0, 5, (3, 3))
    state = np.concatenate([q.ravel() * G, [10.0, -20.0, 30.0]])
    a = rng.normal(0, 1, (12, 12))
    part = a @ a.T * 0.01
    return IntrinsicResult.from_state(1.0, state, 3 * part, G, U_G,
                                      [(BudgetInput("seg1", "segment", 1, "x", 20), part),
                                       (BudgetInput("seg2", "segment", 2, "y", 5), 2 * part)])


def test_dof_by_hand_and_through_any_jacobian():
    res = _result()
    # parts p and 2p (dof 20 and 5) of 3p, g_local's share 0 for angles and offsets: nu = 9 / (1/20 + 4/5)
    assert res.dof[3:] == pytest.approx(9 / (1 / 20 + 4 / 5), rel=1e-12)
    _, jac, jac_g = intrinsic_jacobian(res.state, G)
    np.testing.assert_array_equal(res.welch_satterthwaite(jac, jac_g), res.dof)


def test_correction_and_its_covariance_against_finite_differences():
    res = _result()
    rc = rate_calibration(res, "table", "baseline", "the papers' model", "bit")
    Q = res.state[:9].reshape(3, 3) / G
    np.testing.assert_allclose(rc.P_matrix @ Q, np.eye(3), atol=1e-12)
    np.testing.assert_array_equal(rc.O_vector, res.state[9:])

    def correction(state: np.ndarray, g: float) -> np.ndarray:
        return np.concatenate([np.linalg.inv(state[:9].reshape(3, 3) / g).ravel(), state[9:]])

    h = 1e-6 * np.abs(res.state).max()
    jac = np.column_stack([(correction(res.state + h * e, G) - correction(res.state - h * e, G)) / (2 * h) for e in np.eye(12)])
    jac_g = (correction(res.state, G + 1e-6) - correction(res.state, G - 1e-6)) / 2e-6
    expected = jac @ res.state_cov @ jac.T + np.outer(jac_g, jac_g) * U_G**2
    np.testing.assert_allclose(rc.correction_cov, expected, rtol=1e-6, atol=1e-12 * np.abs(expected).max())
    assert [q.name for q in rc.P][:2] == ["P_xu", "P_xv"] and rc.Q[3].name == "Q_vx"


def test_round_trip_and_refusals(tmp_path):
    rc = rate_calibration(_result(), "table", "baseline", "the papers' model", "bit")
    cal = Calibration("demo", {"id": "dut-1"}, "bit", G, U_G, "dataset.toml [site]", ({"path": "a.csv", "bytes": 3, "sha256": "0" * 64},),
                      {"fit": {}}, "0.0", "2026-11-24T00:00:00Z", (rc,))
    path = cal.write(tmp_path / "calibration.json")
    back = Calibration.read(tmp_path)
    assert back.to_dict() == cal.to_dict()
    assert back.rate(None) is back.rates[0] and back.rate(1.0).model == "baseline"
    with pytest.raises(InputError, match="no rate 2 Hz"):
        back.rate(2.0)
    doc = json.loads(path.read_text())
    doc["rates"][0]["P"] = doc["rates"][0]["P"][:8]
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="not a rotcal calibration: rates/0/P"):
        Calibration.read(path)
    path.write_text('{"schema": "calibration", "version": NaN}')
    with pytest.raises(InputError, match="not a rotcal calibration"):
        Calibration.read(path)


@pytest.mark.parametrize("break_it", [
    lambda d: d["rates"][0]["P"][0].update(std_uncertainty=-1e-9),  # u >= 0
    lambda d: d["rates"][0]["O"][2].update(dof=0.0),  # dof > 0
    lambda d: d["rates"][0]["Q"][1].update(coverage_factor=0.99),  # k >= 1
    lambda d: d["rates"][0].update(frame="lab"),  # a frame the conventions do not name
    lambda d: d["rates"][0]["parameters"][3].update(name="phi_uw"),
    lambda d: d["rates"][0]["correction_covariance"][11].pop(),  # 12 x 12
    lambda d: d["g_local"].update(value=0.0),
    lambda d: d["inputs"][0].update(sha256="0" * 63),
    lambda d: d.update(rates=[]),
    lambda d: d.update(extra=1),
])
def test_write_refuses_what_the_schema_refuses(tmp_path, break_it, monkeypatch):
    """The compiled check a run writes through (fastjsonschema) refuses each
    document jsonschema's reading of schemas/calibration.json refuses, and
    writes nothing then; the untouched document passes both."""
    import fastjsonschema

    rc = rate_calibration(_result(), "table", "baseline", "the papers' model", "bit")
    cal = Calibration("demo", {"id": "dut-1"}, "bit", G, U_G, "dataset.toml [site]", ({"path": "a.csv", "bytes": 3, "sha256": "0" * 64},),
                      {"fit": {}}, "0.0", "2026-11-24T00:00:00Z", (rc,))
    good = cal.to_dict()
    bad = json.loads(json.dumps(good))
    break_it(bad)
    from rotcal.model.calibration import _validator

    assert _validator().is_valid(good) and not _validator().is_valid(bad)
    monkeypatch.setattr(Calibration, "to_dict", lambda self: bad)
    with pytest.raises(fastjsonschema.JsonSchemaException):
        cal.write(tmp_path / "calibration.json")
    assert not (tmp_path / "calibration.json").exists()
