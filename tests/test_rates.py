"""Measured rates against the nominal ones: the logger clock drift (issue 5)."""

import numpy as np
import pytest

from rotcal.timebase.rates import clock_drift, nominal_rate, rate_classes

NOMINAL = np.array([0.01, 0.05, 0.1, 0.5] * 3)


def test_a_common_factor_is_the_drift_and_is_corrected():
    rng = np.random.default_rng(1)
    u = 1e-8 * np.ones(NOMINAL.size)
    measured = NOMINAL / (1 + 200e-6) + rng.normal(0, 1e-8, NOMINAL.size)
    drift = clock_drift(measured, u, NOMINAL)
    assert drift.detected and drift.drift == pytest.approx(200e-6, abs=3 * drift.u_drift)
    assert drift.u_drift < 1e-7
    np.testing.assert_allclose(measured * drift.factor, NOMINAL, rtol=1e-6)
    row = drift.finding("d")
    assert row["value"] == pytest.approx(200.0, abs=0.3) and row["action"].startswith("corrected")


def test_segments_that_disagree_are_not_one_clock():
    measured = NOMINAL * (1 + np.r_[[300e-6] * 6, [-300e-6] * 6])
    drift = clock_drift(measured, 1e-8 * np.ones(NOMINAL.size), NOMINAL)
    assert not drift.consistent and not drift.detected and drift.factor == 1.0
    assert "not off from the nominal ones by one common factor" in drift.warnings()[0]


def test_no_drift_is_not_detected_and_nothing_to_compare_says_so():
    assert not clock_drift(NOMINAL.copy(), 1e-8 * np.ones(NOMINAL.size), NOMINAL).detected
    none = clock_drift(NOMINAL.copy(), np.ones(NOMINAL.size), np.full(NOMINAL.size, np.nan))
    assert none.n == 0 and "cannot be compared" in none.finding("d")["evidence"]


def test_nominal_rates_and_classes():
    assert nominal_rate(0.0500103, (0.01, 0.05, 0.1, 0.5)) == 0.05
    assert nominal_rate(0.07, (0.01, 0.05, 0.1, 0.5)) is None
    np.testing.assert_allclose(rate_classes(np.array([0.1, 0.0100001, 0.1000002, 0.0099999])),
                               [0.1000001, 0.01, 0.1000001, 0.01])
