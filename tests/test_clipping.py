"""The clipping test (rotcal.diagnose.clipping, docs/power.md): the binomial
count and the censoring test against the selected model, their false-alarm
rate under the null, a clip too small for the count that the censoring test
names, and a misfit null model whose noise would fake a clip."""

import json

import numpy as np
import polars as pl
import pytest
from test_power import _null

from rotcal.config import DiagnosisConfig, RunConfig, RunSection
from rotcal.diagnose.clipping import censoring_gain, clip_limits, quantum, stuck_values, successive_noise
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, simulate, write_dataset

ALPHA = DiagnosisConfig().false_alarm
# the acceptance pair offset_drift + axis_tilt of scripts/diagnosis_acceptance.py, seed 5300
MISFIT = ("offset_drift:drift_w=-0.0135044", "axis_tilt:axis=y,tilt_deg=-0.441275")
# a limit 1.5 noise sd above the largest noise-free output of seed 23301 (scripts/power_curves.py's
# clip_request): about 7.5 samples expected beyond it, 8 at it against 2 one quantum inside
SMALL_CLIP = "clipping:clip_high=16699"


def _run(tmp_path, seed, effects):
    spec = SimulationSpec().with_effects(*effects)
    data = write_dataset(simulate(spec, seed), spec, tmp_path / "data")
    run_dataset(data, tmp_path / "out", config=RunConfig(run=RunSection(workers=1)))
    findings = pl.read_parquet(tmp_path / "out" / "diagnosis.parquet").filter(pl.col("detected"))
    params = pl.read_parquet(tmp_path / "out" / "effect_parameters.parquet")
    return set(findings["effect"].to_list()), params, json.loads((data / "truth.json").read_text())


def test_censoring_p_value_is_conservative_without_a_limit():
    """Quantized Gaussian noise (sigma 3 quanta) around a known sinusoid of
    20 sigma, no limit: the combined p-value (binomial and censoring, the
    smaller doubled) falls below 0.1, 0.01 and 0.001 no more often than
    that, over 3,600 channel sides (binomial standard errors 0.005, 0.0017,
    0.0005); with a limit one quantum above the peak, far below 1e-4 / 6."""
    rng = np.random.default_rng(11)
    n, sigma = 3000, 3.0
    mu = 20 * sigma * np.sin(np.linspace(0, 6 * np.pi, n))[:, None] * np.ones(3)
    p = []
    for _ in range(600):
        y = np.round(mu + sigma * rng.standard_normal(mu.shape))
        p += [e.p_value for e in stuck_values(y, 1.0, (mu, np.full(3, sigma)))]
    p = np.array(p)
    for level, slack in ((0.1, 0.015), (0.01, 0.005), (0.001, 0.0015)):
        assert np.mean(p < level) <= level + slack
    clipped = np.minimum(y, 20 * sigma + 1)   # a limit one quantum above the peak: found
    assert min(e.p_value for e in stuck_values(clipped, 1.0, (mu, np.full(3, sigma)))) < ALPHA / 6


def test_successive_noise_ignores_a_slow_misfit():
    """White noise of 8 under a misfit of 60 rms that varies slowly (a
    sinusoid over 500 samples): the residuals' standard deviation is about
    61, the successive-difference estimate 8 within 2 %, segment by segment
    (a jump between segments is not a difference)."""
    rng = np.random.default_rng(3)
    n = 20000
    t = np.arange(n)
    resid = 8 * rng.standard_normal((n, 3)) + 60 * np.sqrt(2) * np.sin(2 * np.pi * t / 500)[:, None]
    segment = t // 5000
    resid += 1000 * segment[:, None]   # each segment its own offset
    est = successive_noise(resid, segment)
    assert est == pytest.approx(np.full(3, 8.0), rel=0.02)


def test_a_clip_too_small_for_the_count_is_named(tmp_path, make_dataset):
    """A limit 1.5 noise sd above the largest output (seed 23301): the
    binomial count alone is nowhere near the threshold (p about 0.2 doubled
    against 1e-4 / 6), yet the diagnosis, whose censoring test weighs where
    the selected model puts each stuck sample, names clipping at the
    simulated limit and nothing else."""
    null = _null(make_dataset, 23301, (SMALL_CLIP,))
    y = null.obs.y
    assert clip_limits(stuck_values(y, quantum(y)), ALPHA) == (None, None)
    found, params, _ = _run(tmp_path, 23301, (SMALL_CLIP,))
    assert found == {"clipping"}
    clip_high = params.filter(pl.col("parameter") == "clip_high")["value"]
    assert clip_high.to_list() == [16699.0]


def test_a_misfit_null_model_does_not_fake_a_clip(tmp_path, make_dataset):
    """offset_drift + axis_tilt, seed 5300: before either effect is modelled
    the null model's noise in v is about 60 (the sensor's 8), and a
    censoring test against it finds four samples sharing v's largest value
    censored (prod pi below 1e-6; the diagnosis makes no censoring test on
    a quantum under 0.05 noise sd). Against the selected model, with the
    local noise, there is no clip: the diagnosis names the two effects only."""
    null = _null(make_dataset, 5300, MISFIT)
    y = null.obs.y
    assert null.sigma[1] > 50
    top = y[:, 1] == y[:, 1].max()
    assert top.sum() == 4
    censored = np.exp(-censoring_gain(null.ev.pred[top, 1], null.sigma[1], y[top, 1], quantum(y)).sum())
    assert censored < 1e-6
    assert successive_noise(y - null.ev.pred, null.obs.segment) == pytest.approx(np.full(3, 8.0), rel=0.03)
    found, _, _ = _run(tmp_path, 5300, MISFIT)
    assert found == {"offset_drift", "axis_tilt"}
