"""The likelihood-ratio yardstick of the power curves (rotcal.diagnose.glr,
scripts/power_curves.py, docs/power.md) against seeded simulations: a large
effect's statistic far beyond its threshold, clean statistics distributed as
chi-square(k), and the clipping statistic zero without samples at a limit."""

import numpy as np
import pytest
from scipy.stats import chi2, kstest

from rotcal.combine.labelled import combine
from rotcal.config import DiagnosisConfig, FitConfig
from rotcal.diagnose import STEP, _start, extensions, observations
from rotcal.diagnose.clipping import quantum
from rotcal.diagnose.glr import clipping_glr, glr, null_fit
from rotcal.diagnose.model import Layout
from rotcal.fit.segments import fit_segments, fits_frame
from rotcal.ingest.dataset import load_dataset
from rotcal.model.results import IntrinsicResult
from rotcal.segment.labelled import segment_by_labels

ALPHA = DiagnosisConfig().false_alarm


def _null(make_dataset, seed, effects=()):
    """The diagnosis's null model (baseline, every parameter fitted) of a
    simulated default-plan dataset."""
    ds = load_dataset(make_dataset(seed, effects=effects))
    samples, segments = segment_by_labels(ds.samples, ds.name)
    fits = fits_frame(fit_segments(samples, segments, FitConfig()), segments, ds.name)
    results = sorted((r for r in combine(fits, ds.meta.g_local, 0.0) if isinstance(r, IntrinsicResult)),
                     key=lambda r: r.rate_hz)
    obs, _, _ = observations(samples, segments, fits, [r.rate_hz for r in results], ds.meta.g_local, 10**9)
    layout = Layout(len(results), extensions(("x", "y", "z"), ("x", "y", "z"), False) + (STEP,))
    return null_fit(obs, layout, _start(layout, results))


def _candidate(fit, key):
    return next(c for c in fit.layout.candidates if c.key == key)


def test_a_large_effect_exceeds_the_threshold_by_its_noncentrality(make_dataset):
    """k3 = 1e-3 on u (the catalogue's upper end): the GLR statistic of the
    true extension is far beyond chi-square(1)'s 1e-4 point (15.1), and near
    the noncentrality the extension's columns predict, the effect's part
    orthogonal to the baseline's columns: sum (x - P x)^2 / sigma^2 with
    x = k3 u^3 y the cubic term."""
    null = _null(make_dataset, 61, ("cubic_nonlinearity:k3_u=0.001",))
    stat, k = glr(null, (_candidate(null, "cubic_nonlinearity@u"),))
    assert k == 1
    assert stat > 10 * chi2.isf(ALPHA, 1)
    d = null.ev.designs[0]
    column = 1e-3 * d.X[:, 4 + list(d.ext).index(null.layout.params(_candidate(null, "cubic_nonlinearity@u"))[0])]
    base = np.column_stack([np.where(d.rate_idx == f, d.X[:, j], 0.0)
                            for f in range(null.layout.n_rates) for j in range(4)])
    orth = column - base @ np.linalg.lstsq(base, column, rcond=None)[0]
    expected = float(orth @ orth) / null.sigma[0] ** 2
    assert stat == pytest.approx(expected, rel=0.35)


def test_clean_statistics_follow_chi_square_with_their_parameters(make_dataset):
    """On three clean datasets every catalogue extension's GLR statistic,
    transformed by chi-square(k)'s survival function (k its parameters: 1 or
    2), is uniform: Kolmogorov-Smirnov p > 0.01 over the about 50 tests, and
    the mean of Lambda / k within 0.6 to 1.5 (its standard error is about 0.2)."""
    pit, ratio = [], []
    for seed in (71, 72, 73):
        null = _null(make_dataset, seed)
        for cand in null.layout.candidates:
            if cand is STEP:
                continue
            stat, k = glr(null, (cand,))
            pit.append(chi2.sf(stat, k))
            ratio.append(stat / k)
    assert len(pit) >= 45
    assert kstest(pit, "uniform").pvalue > 0.01
    assert 0.6 < np.mean(ratio) < 1.5


def test_clipping_statistic_grows_with_the_samples_at_the_limit(make_dataset):
    """Clean, few samples share the largest value and the statistic is that
    of noise (below its Monte Carlo 1e-4 point of about 16 on this plan);
    with the limit at the largest noise-free output, about half the samples
    near the peak sit at it and the statistic is more than ten times that
    point (about 640 on this seed)."""
    clean = _null(make_dataset, 81)
    clipped = _null(make_dataset, 81, ("clipping:below_max=0",))
    assert clipping_glr(clean, quantum(clean.obs.y)) < 16
    assert clipping_glr(clipped, quantum(clipped.obs.y)) > 160
