"""The diagnosis of static recordings (``rotcal.diagnose.static``), on
seeded hand-pose and jig sessions (``tests/handsim.py``) run end to end:
an effect of the catalogue found on its channel with its parameter near
the truth, the refined intrinsic rows written; a clean session with no
finding; the detection limit against its hand derivation; the real
recordings (issue 15 item 5)."""

import numpy as np
import polars as pl
import pytest
from scipy.stats import chi2

from rotcal.combine.multiposition import pose_arrays
from rotcal.combine.poses import references
from rotcal.diagnose.static_model import pose_model
from rotcal.run import run_dataset

from handsim import hand_session, write_session
from testdata import REAL, REPO

MIKOFF = REPO / "tests" / "data" / "corpus" / "mikoff_mpu9150"


def _run(tmp_path, seed, effects=(), **kw):
    frame, truth = hand_session(seed, effects, **kw)
    outcome = run_dataset(write_session(tmp_path / "data", frame), tmp_path / "out")
    return outcome, truth


def _found(outcome) -> list[tuple[str, str]]:
    return outcome.diagnosis.findings.filter("detected").select("effect", "where").rows()


def test_cubic_nonlinearity_of_hand_poses_found_with_its_coefficient(tmp_path):
    """30 hand poses, k3_v = 8e-4: named on channel v alone, k3_v within 3u
    of the truth; the refined rows are written and recommended."""
    outcome, truth = _run(tmp_path, 3, ("cubic_nonlinearity:k3_v=8e-4",))
    assert _found(outcome) == [("cubic_nonlinearity", "channel v (all 30 poses)")]
    (name, value, u), = outcome.diagnosis.parameters.select("parameter", "value", "std_uncertainty").rows()
    print(name, value, u)
    assert name == "k3_v" and abs(value - truth["k3_v"]) < 3 * u and u < 2e-4
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet")
    refined = intrinsic.filter(pl.col("model") == "refined")
    assert refined.height == 9 and refined["recommended"].all()
    assert "## Effect parameters" in (tmp_path / "out" / "report.md").read_text()


def test_thermal_of_hand_poses_found_with_its_coefficients(tmp_path):
    """A warm-up with tco_w = -1.5 counts/K, tcs_w = 6e-5 /K: thermal named
    on channel w alone, both coefficients within 3u."""
    outcome, truth = _run(tmp_path, 4, ("thermal:tco_w=-1.5,tcs_w=6e-5,warmup_k=6,tau_frac=0.25",))
    assert _found(outcome) == [("thermal", "channel w (all 30 poses)")]
    for name, value, u in outcome.diagnosis.parameters.select("parameter", "value", "std_uncertainty").rows():
        print(name, value, u)
        assert abs(value - truth[name]) < 3 * u


def test_clean_hand_poses_have_no_finding_and_finite_limits(tmp_path):
    """No effect, each rest's mean off by a normal 2 counts (an unsteady
    hand: the static fit estimates the excess scatter, the tests are F
    tests): nothing found, nothing refined; every limit finite (the design
    sees each parameter), within a few times the catalogue's largest size
    to test (the scatter raises them: 2.3e-3, 1.4e-3, 0.08 at most here)."""
    outcome, _ = _run(tmp_path, 5, excess=2.0)
    assert pose_model(outcome.static, None).excess
    assert _found(outcome) == []
    assert "refined" not in set(pl.read_parquet(tmp_path / "out" / "intrinsic.parquet")["model"])
    limits = outcome.diagnosis.limits
    assert set(limits) == {f"{p}_{c}" for p in ("k3", "k2", "drift") for c in "uvw"}
    assert all(limits[f"k3_{c}"] < 3e-3 and limits[f"k2_{c}"] < 2e-3 and limits[f"drift_{c}"] < 0.1 for c in "uvw")


def test_jig_offset_drift_found_and_the_limit_matches_its_hand_derivation(tmp_path):
    """24 jig positions (known references, the vector residuals), a drift
    of 0.05 counts/s on u: named on u alone within 3u. On the clean
    session of the same seed, the drift limit of each channel is the
    threshold over the weighted norm of the pose times left after the
    regression on (ref_x, ref_y, ref_z, 1) (the baseline's design), with
    each channel's noise: sqrt(chi2_isf(alpha, 1)) / |(I - P) tau / sigma|."""
    outcome, truth = _run(tmp_path / "drift", 6, ("offset_drift:drift_u=0.05",), n_poses=24, jig=True)
    assert outcome.static.method == "reference"
    assert _found(outcome) == [("offset_drift", "channel u (all 24 poses)")]
    (name, value, u), = outcome.diagnosis.parameters.select("parameter", "value", "std_uncertainty").rows()
    assert name == "drift_u" and abs(value - 0.05) < 3 * u

    clean, _ = _run(tmp_path / "clean", 6, n_poses=24, jig=True)
    poses = clean.static.positions
    assert not np.any(clean.static.fit.excess_cov)
    _, cov = pose_arrays(poses)
    t0 = 0.0  # the session's first sample
    tau = (poses["t_start_ns"].to_numpy() + poses["t_end_ns"].to_numpy()) / 2e9 - t0
    design = np.column_stack([references(poses), np.ones(poses.height)])
    for r, c in enumerate("uvw"):
        sigma = np.sqrt(cov[:, r, r])
        free = tau / sigma - (design / sigma[:, None]) @ np.linalg.lstsq(design / sigma[:, None], tau / sigma, rcond=None)[0]
        expected = np.sqrt(chi2.isf(1e-4, 1)) / np.linalg.norm(free)
        print(c, clean.diagnosis.limits[f"drift_{c}"], expected)
        assert clean.diagnosis.limits[f"drift_{c}"] == pytest.approx(expected, rel=0.03)


def _limits(outcome, prefix: str) -> np.ndarray:
    return np.array([outcome.diagnosis.limits[f"{prefix}_{c}"] for c in "uvw"])


@pytest.mark.real
def test_real_static_recordings_show_nothing_and_say_how_small(tmp_path):
    """Issue 15 item 5 (docs/method.md, "Real recordings diagnosed"): the
    Xsens hand poses show no effect; the
    Xsens limits as documented."""
    xsens = run_dataset(REAL / "imu_tk_xsens", tmp_path / "xsens", REPO / "configs" / "imu_tk_xsens.toml")
    assert _found(xsens) == []
    print(xsens.diagnosis.limits)
    np.testing.assert_allclose(_limits(xsens, "k3"), [1.44e-3, 1.23e-3, 1.71e-3], rtol=0.05)
    np.testing.assert_allclose(_limits(xsens, "drift"), [0.0045, 0.0046, 0.0041], rtol=0.05)
    imucal = run_dataset(REAL / "imucal_session", tmp_path / "imucal", REPO / "configs" / "imucal_session.toml")
    # imucal's six faces determine the six parameters exactly (labels as approximate directions): no
    # residual degree of freedom is left to test an effect, and the recommendation says so
    assert imucal.static.method == "orientation-free" and imucal.diagnosis is None
    assert imucal.recommended.model == "orthogonal" and "baseline model is not determined: 6 static poses" in imucal.recommended.reason


@pytest.mark.parametrize("sensor", range(5))
def test_mikoff_mpu9150_sessions_show_nothing_within_their_limits(sensor, tmp_path):
    """The five MPU-9150 hand-pose sessions (tests/data/corpus): no finding;
    drift limits 3e-4 to 1e-3 m/s^2 per s, k3 limits 2.5e-3 to 1.1e-2
    (4.4e-4 to 9.1e-4 and 3.7e-3 to 1.0e-2 measured: their channels'
    noise model misses its Allan variance, and the pose means are widened
    by the autoregression of their pooled residuals; 3.7e-4 to 7.1e-4 and
    2.9e-3 to 7.3e-3 by each pose's lag-1 and lag-2 form)."""
    outcome = run_dataset(MIKOFF / f"imu{sensor}.log", tmp_path, REPO / "configs" / "mikoff_mpu9150.toml")
    assert _found(outcome) == []
    drift, k3 = _limits(outcome, "drift"), _limits(outcome, "k3")
    print(drift, k3)
    assert np.all((3e-4 < drift) & (drift < 1e-3)) and np.all((2.5e-3 < k3) & (k3 < 1.1e-2))


@pytest.mark.parametrize("seed", [107, 118, 135])
def test_a_slow_offset_wander_is_noise_not_a_drift(tmp_path, seed):
    """Clean hand sessions under a Gauss-Markov wander of the offsets
    (``scripts/noise_coverage.py``'s shape: 470 to 730 s, 1.8 to 3.6
    counts, over 8 counts of white noise), whose poses' offsets the F test
    took for ``offset_drift`` (p 6e-5 to 1e-4 against independent
    scatter): against the wander fitted under both hypotheses the drift
    has p 0.017 to 0.12, so nothing is named."""
    import sys

    sys.path.insert(0, str(REPO / "scripts"))
    from noise_coverage import noise_request

    from rotcal.simulate import SimulationSpec
    from rotcal.simulate.core import dut_noise

    noise = dut_noise(SimulationSpec().with_noise(noise_request("gauss_markov", seed)))
    outcome, _ = _run(tmp_path, seed, noise=noise)
    assert _found(outcome) == []


def test_a_drift_under_white_noise_is_kept_against_the_wander(tmp_path):
    """A drift of 0.025 count/s on w under white noise (seed 2 of
    ``scripts/static_diagnosis_acceptance.py``): the model with it leaves
    scatter beyond the poses' noise, so it is tested against the wander
    (p 8e-4, below the 0.01 at which the evidence favours the effect), and
    named within 3u."""
    outcome, truth = _run(tmp_path, 2, ("offset_drift:drift_w=-0.025",))
    assert _found(outcome) == [("offset_drift", "channel w (all 30 poses)")]
    value, u = outcome.diagnosis.parameters.filter(pl.col("parameter") == "drift_w").select("value", "std_uncertainty").row(0)
    assert abs(value - truth["drift_w"]) < 3 * u
