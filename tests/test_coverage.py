"""Coverage of the reported uncertainties (issue 3, tightened in issue 12):
on simulated clean datasets, for every parameter pooled over rates, the
fraction with |estimate - truth| <= 2 u must lie in the 99.9 % binomial
interval around 95.45 % and the RMS of z = (estimate - truth) / u in its
chi^2 acceptance interval around 1, so that uncertainties 2x too large or
2x too small fail. Small in CI (24 datasets, about 6 s); the 200-dataset
run is ``ROTCAL_SLOW=1`` (and ``scripts/coverage.py``)."""

import numpy as np
import pytest

from uncertainty_coverage import coverage_frame, simulate_errors


def test_acceptance_accepts_honest_and_rejects_dishonest_uncertainties():
    z = np.random.default_rng(3).standard_normal((200, 5, 9))
    honest = coverage_frame(z)
    assert honest["trials"][0] == 1000
    # exact binomial counts 931 and 975 (the normal approximation gives 933 to 976)
    assert honest["interval_low"][0] == 0.931 and honest["interval_high"][0] == 0.975
    assert honest["passed"].all()
    assert not coverage_frame(z * 1.25)["passed"].any()  # uncertainties 20 % too small
    assert not coverage_frame(z * 0.8)["passed"].any()   # 25 % too large
    # with few trials all within 2 u is inside the binomial interval: only the spread catches large u
    few = coverage_frame(z[:24] * 0.5)
    assert few["passed_2u"].all() and not few["passed_spread"].any()


def test_coverage_small():
    z = simulate_errors(24, first_seed=500)
    frame = coverage_frame(z)
    print(frame)
    assert frame["trials"][0] == 120
    assert 0.7 < frame["z_rms_low"][0] < 0.75 and 1.25 < frame["z_rms_high"][0] < 1.35
    assert frame["passed"].all()
    # the same errors against uncertainties 2x too large and 2x too small
    assert not coverage_frame(z / 2)["passed"].any()
    assert not coverage_frame(z * 2)["passed"].any()


@pytest.mark.slow
def test_coverage_200_datasets():
    frame = coverage_frame(simulate_errors(200, first_seed=10_000, workers=2))
    print(frame)
    assert frame["trials"][0] == 1000
    assert frame["passed"].all()
