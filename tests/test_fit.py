"""The per-segment fit (Gaitan 2021 Eq. 17 against the table angle) against
closed-form truth and against repeated simulation."""

import numpy as np
import polars as pl
import pytest

from rotcal.config import FitConfig, RunConfig, RunSection
from rotcal.fit.refusals import arc_deg, refusal
from rotcal.fit.segments import design, fit_segment, linear_fit
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset


def test_noise_free_coefficients_are_exact():
    theta = np.linspace(10.0, 10.0 + 360 * 2.52, 4200)
    truth = np.array([[500.0, -120.0, 16300.0], [-30.0, -16250.0, 80.0], [12.0, 40.0, -35.0]])
    y = design(theta) @ truth.T
    coef, cov, resid = linear_fit(design(theta), y)
    np.testing.assert_allclose(coef, truth, rtol=1e-12, atol=1e-9)
    assert np.abs(resid).max() < 1e-8


def test_lstsq_agrees_with_normal_equations():
    rng = np.random.default_rng(4)
    theta = rng.uniform(0, 720, 3000)
    y = design(theta) @ rng.normal(0, 1e4, (3, 3)).T + rng.normal(0, 8, (3000, 3))
    coef, _, _ = linear_fit(design(theta), y)
    ref = np.linalg.lstsq(design(theta), y, rcond=None)[0].T
    np.testing.assert_allclose(coef, ref, rtol=1e-11)


def test_reported_covariance_matches_the_scatter_of_repeated_fits():
    """Coverage by repetition: 400 noisy fits of one short, non-whole-cycle
    segment; the reported covariance (with channel correlation) must match
    the observed scatter."""
    rng = np.random.default_rng(11)
    theta = 37.0 + 360 * 0.3 * np.arange(300) * 0.06  # 0.3 Hz, 18 s: 5.4 turns
    truth = np.array([[100.0, 2000.0, -1500.0]] * 3)
    noise_cov = np.array([[64.0, 20.0, 0.0], [20.0, 64.0, 0.0], [0.0, 0.0, 25.0]])
    chol = np.linalg.cholesky(noise_cov)
    clean = design(theta) @ truth.T
    est, reported = [], []
    for _ in range(400):
        fit = fit_segment(0, "rotation", 0.3, "commanded", theta, clean + rng.standard_normal((300, 3)) @ chol.T, FitConfig())
        est.append(fit.coef.ravel())
        reported.append(fit.cov)
    observed = np.cov(np.array(est).T)
    mean_reported = np.mean(reported, axis=0)
    np.testing.assert_allclose(np.diag(observed), np.diag(mean_reported), rtol=0.2)
    # the u-v coefficient correlation from correlated noise is carried
    assert abs(observed[0, 3] / np.sqrt(observed[0, 0] * observed[3, 3]) - 20 / 64) < 0.12
    assert abs(mean_reported[0, 3] / np.sqrt(mean_reported[0, 0] * mean_reported[3, 3]) - 20 / 64) < 0.03


def test_refusals_name_the_reason():
    cfg = FitConfig()
    assert "no angle reference" in refusal("rotation", "none", np.zeros(100), cfg)
    assert "too short" in refusal("rotation", "commanded", np.arange(5.0), cfg)
    assert "only 2 static angles" in refusal("static", "commanded", np.repeat([0.0, 90.0], 20), cfg)
    assert "angle range" in refusal("rotation", "commanded", np.linspace(0, 10, 100), cfg)
    assert refusal("rotation", "commanded", np.linspace(0, 400, 100), cfg) is None


def test_a_channel_pinned_at_one_value_is_a_failure_not_a_zero_uncertainty_fit():
    """A channel saturated through a whole segment has no scatter: fitted, it
    would claim zero uncertainty and outweigh every other segment."""
    theta = np.linspace(0.0, 720.0, 400)
    y = design(theta) @ np.array([[100.0, 2000.0, -1500.0]] * 3).T + np.random.default_rng(2).normal(0, 8, (400, 3))
    y[:, 2] = -32768.0
    fit = fit_segment(0, "rotation", 0.5, "commanded", theta, y, FitConfig())
    assert fit.status == "failed"
    assert fit.reason == "channel w holds -32768 in every sample (stuck or saturated): nothing to fit"


def test_a_segment_saturated_by_centripetal_acceleration_leaves_the_rest_of_the_run(tmp_path):
    """5 m off the y axis, 0.5 Hz gives 49 m/s^2 (5 g) along w: w sits at
    -32768 through the whole y rotation at 0.5 Hz. That segment fails with a
    warning (it used to reach the frequency response's omega^2 fit with a
    zero uncertainty and stop the run with a singular matrix); 0.5 Hz is
    still determined by the x and z rotations."""
    spec = SimulationSpec().with_effects("centripetal:axis=y,radius_m=5.0")
    data = write_dataset(simulate(spec, 1), spec, tmp_path / "data")
    outcome = run_dataset(data, tmp_path / "out", config=RunConfig(run=RunSection(workers=1)))
    assert [w for w in outcome.warnings if "stuck or saturated" in w] == [
        "segment 9 (y, 0.5 Hz): channel w holds -32768 in every sample (stuck or saturated): nothing to fit"]
    assert [r.rate_hz for r in outcome.results] == [0.0, 0.01, 0.05, 0.1, 0.5]
    response = pl.read_parquet(tmp_path / "out" / "frequency_response.parquet")
    assert response.filter(pl.col("quantity") == "offset_omega2_slope").height > 0


def test_a_rotation_sampled_at_a_multiple_of_its_rate_is_refused():
    """100 Hz sampled every 60 ms turns exactly 6 times between samples: the
    commanded angles span 430,000 deg but repeat one angle on the circle, so
    offset, sine and cosine cannot be separated (the fit stopped the run
    with a singular matrix)."""
    theta = 37.0 + 360.0 * 100.0 * 0.06 * np.arange(400)
    y = np.random.default_rng(3).normal(0, 8, (400, 3))
    fit = fit_segment(0, "rotation", 100.0, "commanded", theta, y, FitConfig())
    assert fit.status == "failed"
    assert fit.reason == "angle range 0.0 deg is below the 30 deg needed to separate offset and sine terms"
    # an arc across 0 deg counts as the arc it is
    assert refusal("rotation", "commanded", np.linspace(-10.0, 10.0, 100), FitConfig()).startswith("angle range 20.0 deg")
    assert refusal("rotation", "commanded", np.linspace(-100.0, 100.0, 100), FitConfig()) is None


@pytest.mark.parametrize("theta, arc", [
    (np.repeat(np.arange(0.0, 360.0, 15.0), 50), 345.0),   # Geist's steps
    (np.array([0.0, 359.0] * 5), 1.0),                      # two angles 1 deg apart across 0
    (np.array([350.0, 370.0, -10.0, 725.0]), 20.0),         # wound and unwound
    (np.array([0.0, 360.0, 720.0, -1080.0]), 0.0),          # whole turns: one angle
    (36.0 * np.arange(1000) * 100.0 * 0.06 * 10, 0.0),      # 100 Hz sampled every 60 ms: aliased
    (37.0 + 0.0605 * np.arange(30_000), 360.0),            # a constant rotation of several turns
])
def test_arc_the_angles_cover_on_the_circle(theta, arc):
    assert arc_deg(theta) == pytest.approx(arc, abs=0.0605)  # within one step of the rotation
