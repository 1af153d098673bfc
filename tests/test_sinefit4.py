"""Four-parameter sine fit (IEEE Std 1057 / 1241): the rate fitted too, for
segments whose rate is not trusted. It recovers a rate error, its
covariance matches the scatter of repeated fits, and it is chosen in the
run configuration."""

import numpy as np
import polars as pl
import pytest

from rotcal.config import FitConfig, load_config
from rotcal.errors import ConfigError
from rotcal.fit.segments import design, fit_segment
from rotcal.model.physics import INTRINSIC

from testdata import truth_of
from uncertainty_coverage import reduce_dataset

FOUR = FitConfig(sine_fit="four_parameter")


def _z(red, truth):
    t = np.array([truth[p] for p in INTRINSIC])
    return np.array([(r.value - t) / r.std_uncertainty for r in red.results])


def test_recovers_a_rate_error(make_dataset):
    path = make_dataset(71, effects=("rate_error:rate_error=2e-4",))
    truth = truth_of(path)["intrinsic"]
    four = reduce_dataset(path, FOUR)
    rot = four.fits.filter((pl.col("kind") == "rotation") & (pl.col("channel") == "u"))
    error = (rot["rate_fit_hz"] / rot["rate_hz"] - 1).to_numpy()
    u = (rot["u_rate_fit_hz"] / rot["rate_hz"]).to_numpy()
    assert rot.height == 12 and np.all(np.abs(error - 2e-4) < 4 * u)
    assert np.all(u < 2e-6)  # from 1.7e-6 at 0.01 Hz to 3e-8 at 0.5 Hz
    static = four.fits.filter(pl.col("kind") == "static")
    assert (static["rate_fit_hz"] == 0).all() and (static["u_rate_fit_hz"] == 0).all()
    assert np.abs(_z(four, truth)).max() < 4.5
    # the commanded rate, taken as true, biases the fast rates far beyond their uncertainty
    three = reduce_dataset(path)
    assert np.abs(_z(three, truth)[-1]).max() > 20


def test_covariance_matches_the_scatter_of_repeated_fits():
    rng = np.random.default_rng(7)
    n, rate = 800, 0.5
    theta_cmd = 40.0 + 360 * rate * np.arange(n) * 0.06
    theta_true = 40.0 + 360 * rate * (1 + 3e-4) * np.arange(n) * 0.06
    truth = np.array([[100.0, -16000.0, 900.0], [-40.0, 700.0, 16200.0], [12.0, 300.0, -500.0]])
    noise = np.array([[64.0, 16.0, 0.0], [16.0, 64.0, 0.0], [0.0, 0.0, 25.0]])
    chol = np.linalg.cholesky(noise)
    clean = design(theta_true) @ truth.T
    est, cov, rates, u_rates = [], [], [], []
    for _ in range(300):
        fit = fit_segment(0, "rotation", rate, "commanded", theta_cmd, clean + rng.standard_normal((n, 3)) @ chol.T, FOUR)
        est.append(fit.coef.ravel())
        cov.append(fit.cov)
        rates.append(fit.rate_fit_hz)
        u_rates.append(fit.u_rate_fit_hz)
    rates = np.array(rates)
    assert abs(rates.mean() / rate - 1 - 3e-4) < 4 * rates.std() / rate / np.sqrt(300)
    assert rates.std(ddof=1) == pytest.approx(np.mean(u_rates), rel=0.15)
    np.testing.assert_allclose(np.std(est, axis=0, ddof=1), np.sqrt(np.diag(np.mean(cov, axis=0))), rtol=0.15)
    assert np.all(np.abs(np.mean(est, axis=0) - truth.ravel()) < 4 * np.sqrt(np.diag(np.mean(cov, axis=0)) / 300))


def test_a_wrong_rate_label_is_a_failure_row():
    theta_cmd = 360 * 0.1 * np.arange(1000) * 0.06
    y = design(theta_cmd * 1.3) @ np.array([[0.0, 16000.0, 0.0]] * 3).T
    fit = fit_segment(3, "rotation", 0.1, "commanded", theta_cmd, y + np.random.default_rng(1).normal(0, 8, (1000, 3)), FOUR)
    assert fit.status == "failed" and "four-parameter" in fit.reason


def test_sine_fit_is_chosen_in_the_configuration(tmp_path):
    assert load_config().fit.sine_fit == "three_parameter"
    good = tmp_path / "run.toml"
    good.write_text('[fit]\nsine_fit = "four_parameter"\n')
    assert load_config(good).fit.sine_fit == "four_parameter"
    bad = tmp_path / "bad.toml"
    bad.write_text('[fit]\nsine_fit = "five_parameter"\n')
    with pytest.raises(ConfigError, match="sine_fit"):
        load_config(bad)
