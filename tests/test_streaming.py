"""Issue 16, item 1: captures reduced and written in bounded memory.

The streamed simulator must write the very bytes the in-memory one does
(the same random streams drawn in blocks), and the per-segment normal
equations accumulated chunk by chunk must give the in-memory fit."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

import rotcal.blockwise.load as streamed
import rotcal.run.stages as stages
from rotcal.blockwise.segments import stream_segments
from rotcal.config import FitConfig, RunConfig, with_options
from rotcal.fit.normal import NormalSums, ResidualSums, coefficient_covariance
from rotcal.fit.segments import fit_segments, fits_frame
from rotcal.fit.sines import sincos_deg, sine3_fit
from rotcal.ingest.dataset import load_dataset
from rotcal.run import run_dataset
from rotcal.segment import segment_by_labels
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.blocks import streamable, write_streamed
from rotcal.timebase import repair_timebase


def small_spec() -> SimulationSpec:
    spec = SimulationSpec()
    return replace(spec, plan=replace(spec.plan, rotation_samples=2500, rates_hz=(0.05, 0.5)))


@pytest.mark.parametrize("block", [777, 1 << 20])
def test_streamed_simulation_writes_the_same_bytes(tmp_path, block):
    """Blocks of 777 samples split every rotation (2500 samples), the static
    sequences (1200) and the table's 0.1 s ticks (samples 0.06 s apart)
    mid-way; one large block holds each segment whole."""
    spec = small_spec()
    assert streamable(spec, "mcap-cdr")
    memory = write_dataset(simulate(spec, 7), spec, tmp_path / "memory", "mcap-cdr", "dut")
    streamed = write_streamed(spec, 7, tmp_path / "streamed", "dut", block=block)
    for name in ("capture.mcap", "truth.json", "dataset.toml"):
        assert (streamed / name).read_bytes() == (memory / name).read_bytes(), name


def test_only_plain_plans_are_streamed():
    spec = small_spec()
    assert not streamable(spec, "csv")
    assert not streamable(spec.with_effects("centripetal:axis=x,radius_m=0.2"), "mcap-cdr")
    assert not streamable(spec.with_timebase("drop_fraction=0.01"), "mcap-cdr")
    assert not streamable(replace(spec, plan=replace(spec.plan, continuous=True)), "mcap-cdr")


def test_normal_equations_accumulate_across_any_chunks():
    """A rotation segment's samples fed in chunks of random lengths (as a
    capture's chunks cut it) give the in-memory fit to rounding: the sums
    are additive and the lag-1 product is carried across the boundaries.
    The truth of the coefficients is the seeded simulation's own."""
    rng = np.random.default_rng(11)
    n = 50_000
    theta = 123.4 + 360.0 * 0.05 * 0.06 * np.arange(n)
    truth = np.array([[100.0, 1600.0, -20.0], [-50.0, 30.0, 1650.0], [7.0, -12.0, 9.0]])
    s, c = np.sin(np.deg2rad(theta)), np.cos(np.deg2rad(theta))
    channels = tuple(t[0] + t[1] * s + t[2] * c + rng.normal(0.0, 3.0, n) for t in truth)
    coef, cov, rtr, max_abs, lag = sine3_fit(theta, channels)
    cuts = np.r_[0, np.sort(rng.choice(np.arange(1, n), 40, replace=False)), n]
    normal = NormalSums()
    for a, b in zip(cuts[:-1], cuts[1:]):
        normal.add(*sincos_deg(theta[a:b]), [y[a:b] for y in channels])
    streamed, xtx_inv = normal.solve()
    residual = ResidualSums(streamed)
    for a, b in zip(cuts[:-1], cuts[1:]):
        residual.add(*sincos_deg(theta[a:b]), [y[a:b] for y in channels])
    np.testing.assert_allclose(streamed, coef, rtol=1e-9, atol=1e-9 * np.abs(coef).max())
    # entries zero but for rounding (sin and cos orthogonal over whole turns) compare against the largest
    np.testing.assert_allclose(coefficient_covariance(residual.products(), xtx_inv, n), cov, rtol=1e-9,
                               atol=1e-9 * np.abs(cov).max())
    np.testing.assert_allclose(residual.products(), rtr, rtol=1e-9)
    np.testing.assert_allclose(residual.max_abs, max_abs, rtol=1e-9)
    np.testing.assert_allclose(residual.lag, lag, rtol=1e-9)
    # and the fit itself: within 5 standard uncertainties of the simulated truth
    assert np.all(np.abs(coef - truth) < 5 * np.sqrt(np.diag(cov)).reshape(3, 3))


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory):
    """A 300,000-sample MCAP capture of the default plan (rotations of 24,700 samples)."""
    spec = SimulationSpec()
    spec = replace(spec, plan=replace(spec.plan, rotation_samples=24_700))
    return load_dataset(write_streamed(spec, 5, tmp_path_factory.mktemp("long") / "d"))


@pytest.mark.parametrize("block", [4999, 1 << 20])
def test_segments_and_fits_streamed_equal_in_memory(long_capture, block):
    """Segments and fits from the capture's samples read in blocks (4999
    samples: every segment cut by block boundaries, twice a pass) equal
    those of the whole table in memory, to 1e-9 relative."""
    assert long_capture.samples.height == 300_000
    _assert_streamed_fits_equal(long_capture, long_capture.samples, block)


def test_fits_widened_for_correlated_noise_streamed_equal_in_memory(long_capture):
    """With correlated noise (a first-order autoregression, lag-1 0.6, 10
    counts sd, added) both ways widen the covariances from the residuals'
    spectrum pooled across segments (``fit.spectrum``): read in blocks of
    4999 samples, each segment is fitted whole once its blocks are in, so
    the widened uncertainties are the in-memory run's bit for bit (lag-1
    and lag-2 sums carried across blocks had read this noise as a plain
    autoregression, 23 % off)."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(9)
    n = long_capture.samples.height
    noisy = long_capture.samples.with_columns(
        pl.col(c) + np.round(lfilter([1.0], [1.0, -0.6], rng.normal(0, 8.0, n))) for c in ("u", "v", "w"))
    labelled, segments = segment_by_labels(noisy, long_capture.name, long_capture.meta.angle_source)
    fitted = fit_segments(labelled, segments, FitConfig())
    assert all(f.lag1.min() > 0.2 for f in fitted)   # correlated, every segment
    assert all(np.max(f.noise_ratio) > 2 for f in fitted if f.noise_ratio is not None)  # and widened for it
    _assert_streamed_fits_equal(long_capture, noisy, 4999, exact=True)


def _assert_streamed_fits_equal(ds, samples: pl.DataFrame, block: int, exact: bool = False) -> None:
    """The segments and fits of ``samples`` read in blocks of ``block``
    equal those of the whole table in memory: to 1e-9 of each column's
    largest value, or (``exact``) bit for bit."""
    config = FitConfig()
    labelled, segments = segment_by_labels(repair_timebase(samples, ds.name).samples, ds.name, ds.meta.angle_source)
    fits = fits_frame(fit_segments(labelled, segments.filter(pl.col("angle_source") != "none"), config), segments, ds.name)

    def blocks():
        return (samples.slice(a, block) for a in range(0, samples.height, block))

    result = stream_segments(blocks, ds.name, ds.meta.angle_source, config, 100_000)
    streamed_segments, streamed = result.segments, result.fits
    assert_frame_equal(streamed_segments, segments)
    streamed_fits = fits_frame(streamed, streamed_segments, ds.name)
    assert streamed_fits.height == fits.height == 3 * 15
    if exact:
        assert_frame_equal(streamed_fits, fits, check_exact=True)
        return
    numbers = [c for c, d in fits.schema.items() if d == pl.Float64]
    assert_frame_equal(streamed_fits.drop(numbers), fits.drop(numbers))
    for c in numbers:
        scale = np.nanmax(np.abs(fits[c].to_numpy()))
        np.testing.assert_allclose(streamed_fits[c].to_numpy(), fits[c].to_numpy(), rtol=1e-9, atol=1e-9 * scale, err_msg=c)
    for c in ("cov_u", "cov_v", "cov_w"):
        ours, theirs = np.vstack(streamed_fits[c].to_list()), np.vstack(fits[c].to_list())
        np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9 * np.abs(theirs).max(), err_msg=c)


WHOLE = 10**12  # ``[run] stream_above_samples`` that reads any capture whole

# statistics of the difference of two near-equal estimates (consistency checks, the simultaneous solution
# against the per-segment one): rounding of the estimates, ~1e-12, grows by their ratio to the difference
DIFFERENCES = {"z", "chi2", "chi2_per_dof", "p_value", "difference", "difference_over_u", "z_difference"}


def assert_tables_match(ours: Path, theirs: Path, only_theirs: tuple[str, ...] = ()) -> int:
    """Every table of two output directories (but ``only_theirs``, which
    ``ours`` lacks): integers and strings equal, floats within 1e-9 of their
    column's largest magnitude (1e-6 for the statistics of differences); the
    number of tables compared."""
    names = sorted(p.name for p in theirs.glob("*.parquet") if p.name not in only_theirs)
    assert names == sorted(p.name for p in ours.glob("*.parquet"))
    for name in names:
        a, b = pl.read_parquet(ours / name), pl.read_parquet(theirs / name)
        assert a.schema == b.schema and a.height == b.height, name
        floats = [c for c, d in b.schema.items() if d == pl.Float64 or d == pl.List(pl.Float64)]
        # the time base's evidence quotes figures at rounding level (the stamps' scatter about the
        # grid, 1e-8 ms), whose streamed sums round otherwise: its values are compared as floats
        words = ["evidence"] if name == "timebase.parquet" else []
        assert_frame_equal(a.drop(floats + words), b.drop(floats + words), check_exact=True)
        for c in floats:
            x, y = (np.array(f[c].explode().fill_null(np.nan).to_numpy(), float) for f in (a, b))
            assert np.array_equal(np.isnan(x), np.isnan(y)), (name, c)
            scale = np.nanmax(np.abs(y), initial=0.0)
            tol = (1e-6 if c in DIFFERENCES else 1e-9) * scale
            if name == "timebase.parquet":  # scatters zero but for rounding (1e-19 s): within a picosecond
                tol = max(tol, 1e-12)
            assert np.nanmax(np.abs(x - y), initial=0.0) <= tol, (name, c, np.nanmax(np.abs(x - y)) / scale)
    return len(names)


@pytest.fixture(scope="module")
def centripetal_capture(tmp_path_factory):
    """A 243,600-sample MCAP capture of the default plan (rotations of
    20,000 samples) with a centripetal acceleration the diagnosis finds."""
    spec = SimulationSpec()
    spec = replace(spec, plan=replace(spec.plan, rotation_samples=20_000)).with_effects("centripetal:axis=x,radius_m=0.2")
    return write_dataset(simulate(spec, 3), spec, tmp_path_factory.mktemp("centripetal") / "d", "mcap-cdr", "dut")


def test_the_whole_run_streamed_equals_in_memory(centripetal_capture, tmp_path, monkeypatch):
    """``rotcal run`` on a capture read in blocks of 7,777 samples (every
    rotation and static sequence cut by block boundaries), the default,
    publishes the tables of the run with the capture held whole: the
    segments and fits (each segment fitted whole by the same functions: the
    rounding's repeats, the residuals' periodogram pooled across segments),
    the diagnosis on the same thinned samples (it finds the centripetal
    acceleration and the refined model is recommended), the refits of the
    samples less the effect, the static steps' poses and corrections,
    Geist's simultaneous solution from per-segment sums and the noise model
    from the residuals' Allan sums pooled segment by segment."""
    memory = run_dataset(centripetal_capture, tmp_path / "memory", config=with_options(RunConfig(), run={"stream_above_samples": WHOLE}))
    assert memory.recommended.model == "refined"
    assert memory.diagnosis is not None and memory.diagnosis.findings.filter(pl.col("detected"))["effect"].to_list() == ["centripetal"]
    monkeypatch.setattr(streamed, "BLOCK_SAMPLES", 7_777)
    taken = []
    original = stages._from_stream
    monkeypatch.setattr(stages, "_from_stream", lambda ds, s: taken.append(s) or original(ds, s))
    ours = run_dataset(centripetal_capture, tmp_path / "streamed")
    assert len(taken) == 1 and taken[0].n_samples == 243_600  # streamed, not read in memory
    assert ours.notes == memory.notes and ours.warnings == memory.warnings
    assert ours.recommended.model == "refined"
    assert assert_tables_match(tmp_path / "streamed", tmp_path / "memory") == 16
    # the segment fits, their uncertainties and what follows from them: the same numbers, bit for bit
    for name in ("fits", "intrinsic", "uncertainty_budget", "simultaneous", "noise", "poses", "correction"):
        if (tmp_path / "memory" / f"{name}.parquet").exists():
            assert_frame_equal(pl.read_parquet(tmp_path / "streamed" / f"{name}.parquet"),
                               pl.read_parquet(tmp_path / "memory" / f"{name}.parquet"), check_exact=True)


def test_what_the_streamed_path_cannot_take_is_read_in_memory(centripetal_capture, tmp_path):
    """Four-parameter fits read every sample: the capture is read whole, with a note, and the tables are the in-memory run's."""
    four = with_options(RunConfig(), fit={"sine_fit": "four_parameter"}, diagnosis={"enabled": False})
    memory = run_dataset(centripetal_capture, tmp_path / "memory", config=with_options(four, run={"stream_above_samples": WHOLE}))
    ours = run_dataset(centripetal_capture, tmp_path / "streamed", config=four)
    note = "read in memory, not block by block: four-parameter fits ([fit] sine_fit)"
    assert note in ours.notes and tuple(n for n in ours.notes if n != note) == memory.notes
    for p in (tmp_path / "memory").glob("*.parquet"):
        assert pl.read_parquet(tmp_path / "streamed" / p.name).equals(pl.read_parquet(p)), p.name


@pytest.mark.parametrize("stamps", ["regular", "jittered", "two steps"])
def test_the_sample_interval_counted_block_by_block_is_the_median_step(long_capture, stamps):
    """The noise model's sample interval, read in blocks of 4999 samples
    (each block's positive steps counted by value), is
    ``noise.residuals.sample_interval_s`` of the whole table: regular
    stamps, stamps jittered by up to 3 us (thousands of distinct steps),
    and steps of two values half and half (an even count: the mean of
    the two middle ones, half a nanosecond off either)."""
    from rotcal.blockwise.segments import label_runs
    from rotcal.noise.residuals import sample_interval_s

    rng = np.random.default_rng(4)
    samples = long_capture.samples
    t0 = samples["t_ns"][0]
    if stamps == "jittered":
        samples = samples.with_columns(pl.col("t_ns") + rng.integers(0, 3_001, samples.height))
    if stamps == "two steps":  # 299,998 steps: 149,999 of 60 ms and as many of 60 ms + 1 ns
        samples = samples.head(299_999)
        steps = rng.permutation(np.repeat([60_000_000, 60_000_001], 149_999))
        samples = samples.with_columns(t_ns=pl.Series(t0 + np.r_[0, np.cumsum(steps)]))
    distinct = samples["t_ns"].diff().drop_nulls().n_unique()
    assert distinct > 1000 if stamps == "jittered" else distinct == 2 if stamps == "two steps" else True

    def blocks():
        return (samples.slice(a, 4999) for a in range(0, samples.height, 4999))

    assert label_runs(blocks)[2] == sample_interval_s(samples) > 0
