"""Coverage of the reported uncertainties (issue 3): on simulated clean
datasets, for every parameter pooled over rates, the fraction with
|estimate - truth| <= 2 u must lie in the 99.9 % binomial interval around
95.45 %. Small in CI; the 200-dataset run is ``ROTCAL_SLOW=1`` (and
``scripts/coverage.py``)."""

import numpy as np
import pytest

from rotcal.metrology.coverage import coverage_frame, simulate_errors


def test_binomial_interval_accepts_honest_and_rejects_dishonest_uncertainties():
    z = np.random.default_rng(3).standard_normal((200, 5, 9))
    honest = coverage_frame(z)
    assert honest["trials"][0] == 1000
    # exact binomial counts 931 and 975 (the normal approximation gives 933 to 976)
    assert honest["interval_low"][0] == 0.931 and honest["interval_high"][0] == 0.975
    assert honest["passed"].all()
    assert not coverage_frame(z * 1.25)["passed"].any()  # uncertainties 20 % too small
    assert not coverage_frame(z * 0.8)["passed"].any()   # 25 % too large


def test_coverage_small():
    frame = coverage_frame(simulate_errors(12, first_seed=500))
    print(frame)
    assert frame["trials"][0] == 60
    assert frame["passed"].all()
    assert frame["z_rms"].min() > 0.7 and frame["z_rms"].max() < 1.35


@pytest.mark.slow
def test_coverage_200_datasets():
    frame = coverage_frame(simulate_errors(200, first_seed=10_000, workers=2))
    print(frame)
    assert frame["trials"][0] == 1000
    assert frame["passed"].all()
