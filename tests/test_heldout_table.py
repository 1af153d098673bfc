"""Held-out segments of table runs (``diagnose.heldout``): the linearised
leave-one-segment-out prediction against explicit refits, the rank test
against scipy, and the recommendation it gates (refined where an effect
predicts held-out segments, with the figures in calibration.json; the
baseline where a model fits the samples but predicts no held-out segment)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import polars as pl
import pytest
from scipy import stats

from rotcal.combine.heldout import compare, signed_rank
from rotcal.config import RunConfig, RunSection
from rotcal.diagnose import refined_results
from rotcal.diagnose.fitting import fit_model
from rotcal.diagnose.heldout import _press, held_out_units, segments_held_out
from rotcal.diagnose.model import Structure, predict
from rotcal.model.calibration import Calibration
from rotcal.run import run_dataset
from rotcal.run.recommended import recommend_stage
from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.spec import Plan

ONE_WORKER = RunConfig(run=RunSection(workers=1))
TWO_RATES = SimulationSpec(plan=Plan(rates_hz=(0.1, 0.5)))  # 9 segments: each held out in 4 blocks


@pytest.fixture(scope="module")
def delayed(tmp_path_factory):
    """A 0.8 ms delay of channel v (docs/effects.md's small end) on the two-rate plan, seed 5."""
    tmp = tmp_path_factory.mktemp("heldout_table")
    spec = TWO_RATES.with_effects("channel_delay:delay_v_s=0.0008")
    data = write_dataset(simulate(spec, 5), spec, tmp / "data")
    return run_dataset(data, tmp / "out", config=ONE_WORKER), tmp / "out"


def test_press_of_a_unit_is_the_refit_without_it(delayed):
    """Each unit's prediction error is that of the model refitted
    (Gauss-Newton to convergence) on every other unit's samples: to 1e-9 for
    the baseline (linear) and the model with the delay (linearised at its
    optimum), on units of three segments and of both models."""
    final = delayed[0].diagnosis.final
    baseline = fit_model(final.obs, final.layout, final.beta, (), final.clip, Structure(), final.use)
    units = held_out_units(final)
    assert units.max() + 1 == 36  # 9 segments in 4 blocks each
    for model in (baseline, final):
        errors, undetermined = _press(model, units, final.sigma)
        assert undetermined == []
        for k in (0, 13, 35):
            unit = final.use & (units == k)[:, None]
            other = fit_model(final.obs, final.layout, model.beta, model.active, final.clip, model.structure,
                              final.use & ~unit)
            pred = predict(final.obs, other.beta, final.layout, model.active, final.clip, model.structure)
            resid = np.where(unit, final.obs.whitened(final.obs.y - pred, unit), 0.0)
            assert errors[k] == pytest.approx(float(np.sum(resid**2 / final.sigma**2)) / unit.sum(), rel=1e-9)


def test_an_effect_that_predicts_held_out_segments_is_recommended_with_its_figures(delayed):
    outcome, out = delayed
    assert outcome.recommended.model == "refined"
    verdict, unit = segments_held_out(outcome.diagnosis.final)
    assert unit == "segment block" and verdict.better and verdict.p_value < 1e-4 and verdict.wins >= 27
    sentence = "left out one segment block at a time, the refined model predicts the held-out segment blocks better"
    assert sentence in outcome.recommended.reason
    assert all(sentence in rate.reason for rate in Calibration.read(out).rates)


def test_a_model_that_only_fits_its_samples_is_not_recommended(delayed):
    """The delay's model with a cubic nonlinearity of channel w forced in
    (none simulated): it fits the samples at least as well, predicts no
    held-out segment block better by more than chance, and the hook
    recommends the baseline, saying why."""
    outcome, out = delayed
    final = outcome.diagnosis.final
    base = fit_model(final.obs, final.layout, final.beta, (), final.clip, Structure(), final.use)
    cubic = next(c for c in final.layout.candidates if c.key == "cubic_nonlinearity@w")
    forced = fit_model(final.obs, final.layout, base.beta, (cubic,), final.clip, Structure(), final.use)
    assert forced.ev.rss.sum() <= base.ev.rss.sum()
    verdict, _ = segments_held_out(forced)
    assert not verdict.better and verdict.p_value > 0.2
    g = outcome.results[0].g_local
    diagnosis = replace(outcome.diagnosis, final=forced, refined=refined_results(forced, g, 0.0),
                        before={"cubic_nonlinearity": forced.residuals})
    reductions = type("Reductions", (), {"static": None})()
    chosen = recommend_stage(pl.read_parquet(out / "intrinsic.parquet"), outcome.results, ("table",) * len(outcome.results), diagnosis,
                             reductions, ONE_WORKER, ())  # type: ignore[arg-type]
    assert chosen.model == "baseline"
    assert chosen.reason.startswith("left out one segment block at a time, the refined model does not predict")
    assert chosen.reason.endswith("cubic_nonlinearity not modelled in the recommended result")


def test_ranks_where_the_gains_differ_by_decades():
    """Wilcoxon's one-sided signed-rank test as scipy's; on the held-out
    errors of a 4 cm centripetal radius (default plan, seed 40: 3 static
    segments, then 4 rates a decade apart on each axis), where the gain
    grows with the rate squared, the paired t test takes the spread of
    sizes for chance (p = 0.027, within a factor 2 of the level) where the
    ranks see the segments predicted better (p = 9e-4 on these errors to
    four digits)."""
    simple = np.array([0.969, 1.025, 1.065, 1.917, 565.646, 0.969, 0.984, 1.238, 4.58, 2259.143,
                       0.991, 1.009, 1.041, 1.884, 565.412])
    rich = np.array([0.9691, 1.024, 1.008, 1.002, 0.987, 0.969, 0.983, 1.002, 1.017, 1.061,
                     0.991, 1.008, 0.981, 1.017, 0.999])
    ranked = signed_rank(simple, rich)
    expected = stats.wilcoxon(np.log1p(simple) - np.log1p(rich), alternative="greater")
    assert ranked.ranked and ranked.dof == 14 and ranked.wins == 12
    np.testing.assert_allclose([ranked.t, ranked.p_value], [expected.statistic, expected.pvalue], rtol=1e-12)
    assert ranked.better and ranked.p_value < 2e-3
    assert compare(simple, rich).p_value > 0.02
    assert not signed_rank(rich, simple).better


def test_a_segment_that_alone_determines_a_parameter_is_held_out_by_blocks(tmp_path):
    """Two axes (x, z), five rates: each rate's rotation about z alone
    determines its responsivities' x components (and about x, z's), the
    static steps of one axis alone the static result's: every segment is
    cut into blocks, each block predicted from the rest."""
    spec = SimulationSpec(plan=Plan(axes=("x", "z"), rates_hz=(0.01, 0.02, 0.05, 0.1, 0.5), rotation_samples=1500))
    spec = spec.with_effects("cubic_nonlinearity:k3_u=-1e-3")
    outcome = run_dataset(write_dataset(simulate(spec, 3), spec, tmp_path / "data"), tmp_path / "out", config=ONE_WORKER)
    final = outcome.diagnosis.final
    units = held_out_units(final)
    assert units.max() + 1 == 12 and _press(final, units, final.sigma)[1] == list(range(12))
    verdict, unit = segments_held_out(final)
    assert unit == "segment block" and verdict.dof + 1 == 48 and verdict.better
    assert outcome.recommended.model == "refined" and "left out one segment block at a time" in outcome.recommended.reason
