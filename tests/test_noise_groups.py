"""Segments of different noise: Bartlett's test on successive-difference
variances, and the diagnosis whitened where it rejects (rotcal.diagnose.noise).

A table that vibrates more at its higher rates gives noisier segments there;
the diagnosis pooled one noise per channel and read the noisy segments as
misfits (five false ``unexplained`` findings with 30 counts sd added to the
0.5 Hz captures, docs/method.md)."""

from dataclasses import replace

import numpy as np
import polars as pl
import pytest
from scipy import stats
from scipy.signal import lfilter

from rotcal.config import RunConfig, RunSection
from rotcal.diagnose.noise import bartlett
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset


def test_bartlett_equals_scipy_on_sample_variances():
    """With ordinary sample variances (n - 1 degrees of freedom) the
    statistic is scipy's, bit for bit in the p-value's first 12 digits."""
    rng = np.random.default_rng(3)
    groups = [rng.normal(0, s, n) for s, n in ((1.0, 40), (1.3, 55), (0.8, 23), (1.1, 70))]
    var = np.array([g.var(ddof=1) for g in groups])
    dof = np.array([g.size - 1 for g in groups], float)
    assert bartlett(var, dof) == pytest.approx(stats.bartlett(*groups).pvalue, rel=1e-12)


def test_successive_difference_variances_keep_bartletts_false_alarm_rate():
    """The von Neumann estimate's degrees of freedom, 2 m^2 / (3 m - 1)
    for m differences, hold the test at its rate: 4000 sets of five
    white-noise groups of 50 to 400 samples, p < 0.05 in 5 % of them
    (binomial sd 0.34 %; with m - 1 degrees of freedom instead, 17 %)."""
    rng = np.random.default_rng(11)
    sizes = np.array([50, 80, 120, 200, 400])
    p = []
    for _ in range(4000):
        var = np.array([np.mean(np.diff(rng.normal(0, 2.0, n)) ** 2) / 2 for n in sizes])
        m = sizes - 1.0
        p.append(bartlett(var, 2 * m**2 / (3 * m - 1)))
    assert abs(np.mean(np.array(p) < 0.05) - 0.05) < 0.012


def _noisier(seed: int, extra: dict[float, float], tmp_path, effects=(), phi: float = 0.0):
    """A default-plan simulation with noise of ``extra[rate]`` counts sd
    added at those rates (rounded, as the converter's output is), a
    first-order autoregression of coefficient ``phi`` (white for 0), run."""
    spec = SimulationSpec().with_effects(*effects)
    sim = simulate(spec, seed)
    rng = np.random.default_rng(seed + 1000)
    sd = sim.samples["rate_hz"].replace_strict(extra, default=0.0, return_dtype=pl.Float64).to_numpy()
    added = {c: np.round(lfilter([1.0], [1.0, -phi], rng.normal(0.0, np.sqrt(1 - phi**2), sd.size)) * sd)
             for c in ("u", "v", "w")}
    sim = replace(sim, samples=sim.samples.with_columns(pl.col(c) + added[c] for c in added))
    data = write_dataset(sim, spec, tmp_path / "data")
    run_dataset(data, tmp_path / "out", config=RunConfig(run=RunSection(workers=1)))
    return (pl.read_parquet(tmp_path / "out" / "diagnosis.parquet"),
            pl.read_parquet(tmp_path / "out" / "effect_parameters.parquet"))


@pytest.mark.parametrize(("seed", "extra"), [(7, {0.5: 30.0}), (14, {0.01: 20.0, 0.05: 20.0})])
def test_noisier_rates_raise_no_finding(tmp_path, seed, extra):
    """30 counts sd more at 0.5 Hz (8 elsewhere): before the whitening,
    unexplained misfits in all three channels (seed 7)."""
    findings, params = _noisier(seed, extra, tmp_path)
    assert not findings["detected"].any(), findings.filter(pl.col("detected"))
    assert params.height == 0


def test_a_concealed_effect_is_measured_where_the_noise_differs(tmp_path):
    """A 1 ms channel_delay of v, concealed in each segment's phase, is
    named alone and measured within 3 standard uncertainties with 30 counts
    sd more at 0.5 Hz, where the delay shows most."""
    findings, params = _noisier(11, {0.5: 30.0}, tmp_path, ("channel_delay:delay_v_s=0.001",))
    assert findings.filter(pl.col("detected"))["effect"].to_list() == ["channel_delay"]
    delay = params.filter(pl.col("parameter") == "delay_v_s").row(0, named=True)
    assert abs(delay["value"] - 0.001) < 3 * delay["std_uncertainty"]


CORRELATED = {rate: 10.0 for rate in (0.0, 0.01, 0.05, 0.1, 0.5)}


@pytest.mark.parametrize("seed", [7, 8])
def test_correlated_noise_raises_no_finding(tmp_path, seed):
    """10 counts sd of an autoregression (phi 0.6) added everywhere: the
    samples are correlated from one to the next (lag-1 about 0.37), noise
    the fits' uncertainties carry, so no finding: Geist's Appendix B test
    is taken after the recording's own autoregression. Before the
    diagnosis filtered it (``noise.whitening``), 12 unexplained findings in
    each (segment misfits, harmonics, rate dependence); before the tests
    took the noise model, the three static-step correlation rows."""
    findings, params = _noisier(seed, CORRELATED, tmp_path, phi=0.6)
    found = findings.filter(pl.col("detected"))
    assert found.height == 0, found
    assert params.height == 0


def test_a_concealed_effect_is_measured_in_correlated_noise(tmp_path):
    """A 0.1 m centripetal radius under the same correlated noise: named
    alone (beside Geist's correlation rows) and measured within 3 standard
    uncertainties."""
    findings, params = _noisier(13, CORRELATED, tmp_path, ("centripetal:axis=y,radius_m=0.1",), phi=0.6)
    named = findings.filter(pl.col("detected") & (pl.col("effect") != "unexplained"))["effect"].to_list()
    assert named == ["centripetal"]
    radius = params.filter(pl.col("parameter") == "radius_m").row(0, named=True)
    assert abs(radius["value"] - 0.1) < 3 * radius["std_uncertainty"]


def test_whitening_filters_each_segment_from_its_first_sample():
    """x*_i = scale_i (x_i - phi_i x_i-1) / sqrt(1 - phi_i^2), phi 0 at a
    segment's first sample, on the whole observations and on a design's
    used rows (a row whose predecessor is not used starts afresh); an
    AR(1) series so filtered is white with the series' variance."""
    from rotcal.diagnose.geometry import Whitening, filtered

    rng = np.random.default_rng(4)
    n, phi = 200_000, 0.7
    x = lfilter([1.0], [1.0, -phi], rng.normal(0, np.sqrt(1 - phi**2), (n, 3)), axis=0)
    out = filtered(x, np.ones((n, 3)), np.full((n, 3), phi))
    assert abs(np.mean(out[1:, 0] * out[:-1, 0])) < 0.01 and abs(out.var() - 1) < 0.02
    explicit = (x[1:] - phi * x[:-1]) / np.sqrt(1 - phi**2)
    np.testing.assert_allclose(out[1:], explicit, rtol=1e-12)
    w = Whitening(np.full((6, 3), 2.0), np.where(np.arange(6)[:, None] == 3, 0.0, 0.5) * np.ones((1, 3)))
    scale, phis = w.rows(np.array([0, 1, 2, 4, 5]), 1)
    assert scale.tolist() == [2.0] * 5 and phis.tolist() == [0.0, 0.5, 0.5, 0.0, 0.5]
