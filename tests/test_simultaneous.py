"""Geist 2017 section 3: the simultaneous least-squares solution over all
segments of a rate agrees with the per-segment solution within the
uncertainties, and both find the truth."""

import numpy as np
import pytest

from rotcal.config import FitConfig
from rotcal.metrology.simultaneous import simultaneous, simultaneous_frame
from rotcal.model.physics import INTRINSIC
from rotcal.simulate import DutSpec, SimulationSpec

from testdata import truth_of
from uncertainty_coverage import reduce_dataset

NOISE_FREE = SimulationSpec(dut=DutSpec(noise_std=0.0, integer_output=False))


def _both(path, fit=FitConfig()):
    red = reduce_dataset(path, fit)
    meta = red.data.meta
    sim = simultaneous(red.samples, red.fits, meta.g_local, meta.g_local_uncertainty, fit.sine_fit == "four_parameter")
    return red, sim


def test_simultaneous_agrees_with_per_segment_and_truth(make_dataset):
    path = make_dataset(31)
    red, sim = _both(path)
    frame = simultaneous_frame(sim, red.results, "ds", "bit")
    assert frame.height == 45
    # the same data, two least-squares routes: differences are a small fraction of u
    assert np.abs(frame["difference_over_u"].to_numpy()).max() < 0.5
    np.testing.assert_allclose(frame["std_uncertainty"], frame["per_segment_std_uncertainty"], rtol=0.05)
    truth = np.array([truth_of(path)["intrinsic"][p] for p in INTRINSIC])
    for res in sim:
        assert np.all(np.abs(res.value - truth) < 4.5 * res.std_uncertainty)
        np.testing.assert_allclose(sum(res.budget.values()), res.std_uncertainty**2, rtol=1e-9)


def test_simultaneous_is_exact_on_noise_free_data(make_dataset):
    path = make_dataset(32, spec=NOISE_FREE)
    _, sim = _both(path)
    truth = np.array([truth_of(path)["intrinsic"][p] for p in INTRINSIC])
    for res in sim:
        np.testing.assert_allclose(res.value, truth, rtol=1e-10, atol=1e-9)


def test_simultaneous_with_fitted_rates_agrees_within_uncertainty(make_dataset):
    """With the four-parameter fit the simultaneous solution shares the
    components across segments and so pins each segment's rate better: it is
    the more precise of the two, and their difference is within the
    uncertainty of the difference, sqrt(u_per_segment^2 - u_simultaneous^2)."""
    path = make_dataset(33, effects=("rate_error:rate_error=2e-4",))
    red, sim = _both(path, FitConfig(sine_fit="four_parameter"))
    frame = simultaneous_frame(sim, red.results, "ds", "bit")
    u_sim, u_seg = frame["std_uncertainty"].to_numpy(), frame["per_segment_std_uncertainty"].to_numpy()
    assert np.all(u_sim <= u_seg * 1.01)
    assert np.all(np.abs(frame["difference"].to_numpy()) <= 2 * u_seg)
    u_diff = np.sqrt(np.clip(u_seg**2 - u_sim**2, 0, None))
    big = u_diff > 0.1 * u_seg
    assert np.all(np.abs(frame["difference"].to_numpy()[big]) <= 4 * u_diff[big])
    truth = np.array([truth_of(path)["intrinsic"][p] for p in INTRINSIC])
    for res in sim:
        assert np.all(np.abs(res.value - truth) < 4.5 * res.std_uncertainty)


@pytest.mark.parametrize("axes", [("x", "y"), ("x",)])
def test_missing_axes_give_a_failure_not_a_crash(make_dataset, axes):
    from rotcal.metrology.simultaneous import segment_samples, simultaneous_rate
    from rotcal.model.results import Failure
    red = reduce_dataset(make_dataset(31))
    segs = [s for s in segment_samples(red.samples, red.fits, 0.1, False) if s.axis in axes]
    out = simultaneous_rate(0.1, segs, 9.80101, 3e-5)
    if len(axes) == 2:
        assert not isinstance(out, Failure)
    else:
        assert isinstance(out, Failure) and "unmeasured" in out.reason


def test_a_wrong_model_makes_the_two_solutions_disagree(make_dataset):
    """A rate error fitted with the commanded rate: each route weights the
    misfit its own way, and at 0.5 Hz they part far beyond the uncertainties."""
    path = make_dataset(33, effects=("rate_error:rate_error=2e-4",))
    red, sim = _both(path)
    frame = simultaneous_frame(sim, red.results, "ds", "bit")
    fast = frame.filter(frame["rate_hz"] == 0.5)
    assert np.abs(fast["difference_over_u"].to_numpy()).max() > 20
    assert np.abs(frame.filter(frame["rate_hz"] == 0.0)["difference_over_u"].to_numpy()).max() < 0.5  # static steps: exact angles


@pytest.mark.parametrize("seed, spec", [(31, SimulationSpec()), (32, NOISE_FREE)])
def test_the_fits_sums_give_the_solution_of_the_samples(make_dataset, seed, spec):
    """An in-memory run solves its three-parameter segments from the sums
    their fits left (``fit.normal.SineSums``) instead of passing over the
    samples every iteration: the same normal equations, so the same solution
    to rounding (and, noise-free, the truth)."""
    from rotcal.fit import fit_segments
    from rotcal.metrology.simultaneous import SegmentSums, segment_samples
    from rotcal.segment import segment_by_labels

    path = make_dataset(seed, spec=spec)
    red, sim = _both(path)
    data = red.data
    samples, segments = segment_by_labels(data.samples, data.name, data.meta.angle_source)
    sums = {f.segment: f.sums for f in fit_segments(samples, segments, FitConfig(), workers=1) if f.sums is not None}
    assert all(isinstance(s, SegmentSums) for s in segment_samples(red.samples, red.fits, 0.1, False, sums))
    from_sums = simultaneous(red.samples, red.fits, data.meta.g_local, data.meta.g_local_uncertainty, False, sums)
    assert [r.rate_hz for r in from_sums] == [r.rate_hz for r in sim]
    truth = np.array([truth_of(path)["intrinsic"][p] for p in INTRINSIC])
    for a, b in zip(from_sums, sim):
        np.testing.assert_allclose(a.value, b.value, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(a.std_uncertainty, b.std_uncertainty, rtol=1e-9, atol=1e-15)
        if spec is NOISE_FREE:
            np.testing.assert_allclose(a.value, truth, rtol=1e-10, atol=1e-9)
