"""Diagnose: where a recording departs from the papers' model, which physics
of docs/effects.md explains it, the model extended by it and refitted, and what
remains unexplained.

1. The null model (``model``): the fitted intrinsic model of every rate,
   simulated for every sample.
2. Clipping first (``clipping``): a pile of samples at an extreme (the
   binomial count) is set aside, since every other fit would be biased by
   it; after the selection (3), a censoring test against the selected model
   finds the smaller clips, and the selection is redone without them.
3. Forward selection: each catalogue extension (per axis or channel) and an
   offset step at the most likely time is scored by the chi-square it would
   remove; the one with the best BIC among those significant at the stated
   false-alarm rate is added, the model refitted (Gauss-Newton), and the rest
   scored again. Competing explanations of one signature are so decided by
   evidence, never by the order of a list. Backward elimination then drops
   any extension the others made redundant.
4. The offset effects and the step against the offsets' measured wander
   (``wander``), every extension against the noise's measured density at
   its signature's frequencies (``spectral``).
5. Scans of the final residuals (``scans``) for structure no catalogue
   effect explains: tones, rotation harmonics, segment misfits and trends,
   static-step correlation and normality (Geist 2017 Appendix B), and
   responsivity changing with rate, each against the noise the recording
   shows (``scans``, ``misfits``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import polars as pl

from rotcal.config import DiagnosisConfig
from rotcal.diagnose.candidates import STEP, extensions
from rotcal.diagnose.clipping import clip_limits, quantum, stuck_values, successive_noise
from rotcal.diagnose.design import with_columns
from rotcal.diagnose.fitting import ModelFit, Score, chi2_sf, fit_model, score, swap_bic, without
from rotcal.diagnose.misfits import SegmentNoise, residual_autoregression, segment_scan, static_step_scan
from rotcal.diagnose.model import Layout, Observations, Structure, predict
from rotcal.diagnose.noise import whitening
from rotcal.diagnose.observed import observations
from rotcal.diagnose.offset_reentry import taken_back
from rotcal.diagnose.offset_wander import wander_tested
from rotcal.diagnose.reconstructed import with_phases_free, with_reconstructed_angles
from rotcal.diagnose.scans import (
    Residuals,
    Unexplained,
    harmonic_scan,
    p_is,
    step_scan,
    tone_scan,
)
from rotcal.diagnose.spectral import against_spectrum
from rotcal.diagnose.step_exchange import step_or_effect
from rotcal.diagnose.wander import OffsetNoise, against_wander
from rotcal.model.effects import LimitEffect, catalogue, listed
from rotcal.model.effects.base import Candidate
from rotcal.model.physics import AXES, CHANNELS
from rotcal.model.results import IntrinsicResult, whole_fit_input
from rotcal.tables import conform, schema


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """The diagnosis of one dataset: the findings and effect-parameter tables,
    the refined intrinsic results, and the final fit with, per finding, the
    residuals of the model without it (for the report)."""

    findings: pl.DataFrame
    parameters: pl.DataFrame
    refined: tuple[IntrinsicResult, ...]
    final: ModelFit
    before: dict[str, np.ndarray]   # finding -> residuals of the model without it
    samples_available: int          # in the fitted segments; the model's are ``final.obs.n``
    phases: pl.DataFrame | None = None  # the segments whose angles were reconstructed (``reconstructed``)


def _start(layout: Layout, results: list[IntrinsicResult]) -> np.ndarray:
    """Start from the baseline: each rate's combined offsets and responsivities."""
    beta = np.zeros(len(layout.names))
    for f, res in enumerate(results):
        layout.offsets(beta)[f] = res.state[9:]
        layout.responsivity(beta)[f] = res.state[:9].reshape(3, 3)
    return beta


def _residuals(fit: ModelFit, output_unit: str) -> Residuals:
    m = fit.obs.motion
    # each sample's rate as its result names it (a reconstructed rotation runs at its segment's own fitted rate)
    return Residuals(m.t_s, fit.ev.resid, fit.use, fit.sigma, fit.obs.segment, m.axis_idx, fit.obs.rates[fit.obs.rate_idx],
                     m.rotating, m.theta_cmd_deg, output_unit, fit.obs.run)


def _clip_mask(fit: ModelFit, clip: tuple[float | None, float | None], margin_sigma: float = 5.0) -> np.ndarray:
    """Samples a clip can have touched: those at the limit, and those whose
    modelled value (not the noisy observation, which would bias the rest)
    lies within ``margin_sigma`` of it."""
    obs = fit.obs
    pred = predict(obs, fit.beta, fit.layout, fit.active, (None, None), fit.structure)
    use = np.ones_like(obs.y, bool)
    low, high = clip
    if high is not None:
        use &= (obs.y < high) & (pred < high - margin_sigma * obs.sample_noise(fit.sigma))
    if low is not None:
        use &= (obs.y > low) & (pred > low + margin_sigma * obs.sample_noise(fit.sigma))
    return use


def _clipped(fit: ModelFit, clip: tuple[float | None, float | None]) -> ModelFit:
    """The model refitted with the output limits ``clip`` and without the
    samples they can have touched (twice: the mask follows the refit)."""
    if all(v is None for v in clip):
        return fit
    for _ in range(2):
        fit = fit_model(fit.obs, fit.layout, fit.beta, fit.active, clip, fit.structure, _clip_mask(fit, clip))
    return fit


@dataclass(frozen=True)
class StepScore(Score):
    step_t_s: float = 0.0


def _step_score(fit: ModelFit, alpha: float) -> StepScore | None:
    """Score of an offset step at the time the residuals make most likely;
    its false-alarm probability accounts for the scan over time. None where
    that probability is not below ``alpha``: such a step is never selected,
    and its score would cost the step column's products with the design."""
    t, _, p = step_scan(_residuals(fit, ""))
    if p >= alpha:
        return None
    after = (fit.obs.motion.t_s >= t).astype(float)[:, None]
    extra = [(np.array([fit.layout.index[f"step_{c}"]]), after) for c in CHANNELS]
    ev = with_columns(fit.ev, extra)
    s = score(fit, (STEP,), p_value=p, ev=ev, extra_params=1)
    return StepScore(s.candidate, s.chi2, s.p_value, s.delta_bic, s.rss, t)


def _exchange(fit: ModelFit, candidates: tuple[Candidate, ...]) -> ModelFit:
    """Replace a selected extension by an unselected catalogue one wherever
    that lowers BIC: forward selection is greedy, and a structure chosen
    early (an offset step where axis tilt and drift overlap) can shadow the
    physics that explains the data better once everything is modelled."""
    while True:
        best = None
        for drop in fit.active:
            for add in candidates:
                if add in fit.active:
                    continue
                bic = swap_bic(fit, drop, add)
                if bic < fit.bic - 1.0 and (best is None or bic < best[0]):
                    best = (bic, drop, add)
        if best is None:
            return fit
        _, drop, add = best
        active = tuple(c for c in fit.active if c is not drop) + (add,)
        structure = fit.structure if STEP in active else Structure()
        trial = fit_model(fit.obs, fit.layout, fit.beta, active, fit.clip, structure, fit.use)
        if trial.bic >= fit.bic:
            return fit
        fit = trial


def _without_needless_step(fit: ModelFit) -> ModelFit:
    """The model refitted without its offset step where that lowers BIC. A
    step chosen early can hold the catalogue effect it mimics at a wrong
    optimum where the step looks needed: a step taken before the axis tilt
    of the first axis's segments leaves the tilt's sign free (it converged
    to -5 deg for +5), and at that optimum the step's Wald test keeps it."""
    if STEP not in fit.active:
        return fit
    trial = without(fit, (STEP,))
    return trial if trial.bic < fit.bic else fit


def _select(fit: ModelFit, candidates: tuple[Candidate, ...], alpha: float) -> ModelFit:
    """Forward selection by BIC among extensions significant at ``alpha``,
    an exchange pass (``_exchange``), the offset step refitted away where
    BIC prefers (``_without_needless_step``), then backward elimination
    (Wald) of any extension the others made redundant."""
    while True:
        scores: list[Score] = [score(fit, (c,)) for c in candidates if c not in fit.active]
        step = _step_score(fit, alpha) if STEP not in fit.active else None
        if step is not None:
            scores.append(step)
        eligible = [s for s in scores if s.p_value < alpha and s.delta_bic < 0]
        if not eligible:
            break
        best = min(eligible, key=lambda s: (s.delta_bic, s.candidate.key))
        structure = Structure(step_t_s=best.step_t_s) if isinstance(best, StepScore) else fit.structure
        fit = fit_model(fit.obs, fit.layout, fit.beta, fit.active + (best.candidate,), fit.clip, structure, fit.use)
    fit = _without_needless_step(_exchange(fit, candidates))
    while fit.active:
        wald = []
        for c in fit.active:
            value, block = fit.param_block(c)
            wald.append((chi2_sf(value @ np.linalg.pinv(block) @ value, value.size), c.key, c))
        p, _, worst = max(wald)
        if p < alpha:
            break
        fit = without(fit, (worst,))
    return fit


def rate_dependence(final: ModelFit, alpha: float, output_unit: str,
                    baseline: tuple[IntrinsicResult, ...] = ()) -> list[Unexplained]:
    """Whether the responsivity matrices of the rates differ beyond their
    uncertainties (Wald test of R_f = R_0 for every rate f), after every
    modelled effect: a frequency response no catalogue effect explains.
    The whole-model fit takes the noise as white at the rotation's
    frequencies; each difference's variance is widened to the ``baseline``
    results' (from the segment fits, which carry the noise's measured
    spectrum), where larger, keeping the fit's correlations."""
    layout, m = final.layout, final.layout.n_rates
    if m < 2:
        return []
    names = [[layout.index[f"R.{f}.{r}.{c}"] for r in range(3) for c in range(3)] for f in range(m)]
    pos = [np.searchsorted(final.idx, n) for n in names]
    cov = final.covariance()
    diff = np.concatenate([final.beta[names[f]] - final.beta[names[0]] for f in range(1, m)])
    jac = np.zeros((diff.size, final.idx.size))
    for f in range(1, m):
        rows = slice(9 * (f - 1), 9 * f)
        jac[rows, pos[f]] = np.eye(9)
        jac[rows, pos[0]] -= np.eye(9)
    cov_diff = jac @ cov @ jac.T
    by_rate = {r.rate_hz: r.state_cov[:9, :9] for r in baseline}
    if all(float(rate) in by_rate for rate in final.obs.rates):
        # the baseline's rates are independent fits: Var(R_f - R_0) = Var(R_f) + Var(R_0)
        base = np.concatenate([np.diag(by_rate[float(final.obs.rates[f])]) + np.diag(by_rate[float(final.obs.rates[0])])
                               for f in range(1, m)])
        widen = np.sqrt(np.maximum(1.0, base / np.where(np.diag(cov_diff) > 0, np.diag(cov_diff), np.inf)))
        cov_diff = cov_diff * np.outer(widen, widen)
    stat = float(diff @ np.linalg.pinv(cov_diff) @ diff)
    p = chi2_sf(stat, diff.size)
    if p >= alpha:
        return []
    sd = np.sqrt(np.clip(np.diag(cov_diff), 0.0, None))  # 0 where clipping left a component undetermined: no z
    k = int(np.argmax(np.abs(diff) / np.where(sd > 0, sd, np.inf)))
    f, rc = 1 + k // 9, k % 9
    rate = final.obs.rates[f]
    return [] if sd[k] == 0 else [Unexplained(
        "rate_dependence", f"rate {rate:g} Hz against rate {final.obs.rates[0]:g} Hz, channel {CHANNELS[rc // 3]}",
        f"the responsivity changes with rate beyond its uncertainty: component {AXES[rc % 3]} of {CHANNELS[rc // 3]} "
        f"at {rate:g} Hz differs by {diff[k]:+.3g} ± {sd[k]:.2g} {output_unit} per g "
        f"(chi-square {stat:.0f} on {diff.size}; {p_is(p)})", p, np.zeros(3), 0)]




def refined_results(final: ModelFit, g_local: float, g_uncertainty: float) -> tuple[IntrinsicResult, ...]:
    """Each rate's intrinsic parameters from the final model, with the
    covariance it shares with the modelled effects' parameters."""
    layout = final.layout
    cov = final.covariance()
    out = []
    for f, rate in enumerate(final.obs.rates):
        names = [f"R.{f}.{r}.{c}" for r in range(3) for c in range(3)] + [f"O.{f}.{r}" for r in range(3)]
        idx = np.array([layout.index[n] for n in names])
        pos = np.searchsorted(final.idx, idx)
        state, state_cov = final.beta[idx], cov[np.ix_(pos, pos)]
        # the model fits every sample at once: its noise is one input group, not split per segment
        fit_input = whole_fit_input("model fit", float(final.n_total - final.n_params))
        out.append(IntrinsicResult.from_state(float(rate), state, state_cov, g_local, g_uncertainty, [(fit_input, state_cov)]))
    return tuple(out)


def _modelled(obs: Observations, layout: Layout, results: list[IntrinsicResult], cands: tuple[Candidate, ...],
              alpha: float) -> tuple[ModelFit, tuple[float | None, float | None], list, float]:
    """The selected model, from the baseline ``results``, with its output
    limits, their evidence and the output quantum: a pile at an extreme set
    aside first; after the selection, the censoring test against the
    selected model, and the selection redone without what it found."""
    fit = fit_model(obs, layout, _start(layout, results), (), (None, None), Structure(), np.ones_like(obs.y, bool))
    q = quantum(obs.y)
    evidence = stuck_values(obs.y, q)   # the binomial count, which needs no model
    clip = clip_limits(evidence, alpha)
    final = _select(_clipped(fit, clip), cands, alpha)
    if all(v is None for v in clip):   # the censoring test, against the selected model (``clipping``)
        noise = np.minimum(final.sigma, successive_noise(obs.whitened(obs.y - final.ev.pred), obs.run))
        evidence = stuck_values(obs.y, q, (final.ev.pred, obs.sample_noise(noise)))
        clip = clip_limits(evidence, alpha)
        if any(v is not None for v in clip):
            final = _select(_clipped(final, clip), cands, alpha)
    if any(v is not None for v in clip):
        final = fit_model(obs, layout, final.beta, final.active, clip, final.structure, _clip_mask(final, clip))
    return final, clip, evidence, q


def diagnose(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame,
             results: tuple[IntrinsicResult, ...], dataset: str, output_unit: str,
             g_uncertainty: float, angles_measured: bool, config: DiagnosisConfig,
             phases: pl.DataFrame | None = None, *, random_walk: tuple[float, ...] = ()) -> Diagnosis | None:
    """Diagnose one dataset from its samples, segments, fits and baseline
    results; None when it has no fitted table segments. ``phases``: the
    rotation segments without a table angle, whose angles are reconstructed
    from their solved phases (``reconstructed``); the effects those angles
    absorb are then not tested. ``random_walk``: the noise model's random
    walk coefficient K per channel (``rotcal.noise``), part of the offsets'
    noise the offset effects are tested against (``wander``)."""
    from rotcal.diagnose.findings import catalogue_rows, limit_rows, scan_row, step_row

    results = tuple(sorted(results, key=lambda r: (abs(r.rate_hz), r.rate_hz)))
    if not results:
        return None
    g_local = results[0].g_local
    absorbed: frozenset[str] = frozenset()
    if phases is not None and phases.height:
        samples, segments = with_reconstructed_angles(samples, segments, phases)
        absorbed = frozenset(e.name for e in catalogue() if e.absorbed_by_own_phase)
    built = observations(samples, segments, fits, [r.rate_hz for r in results], g_local, config.max_samples)
    if built is None:
        return None
    obs, step_id, n_all = built
    m = obs.motion
    rotating_axes = tuple(AXES[a] for a in sorted(set(m.axis_idx[m.rotating].tolist())))
    all_axes = tuple(AXES[a] for a in sorted(set(m.axis_idx.tolist())))
    logged = frozenset() if m.temperature_c is None else frozenset({"temperature_c"})
    cands = tuple(c for c in extensions(rotating_axes, all_axes, angles_measured, logged) if c.effect not in absorbed)
    layout = Layout(len(results), cands + (STEP,))
    alpha = config.false_alarm
    final, clip, evidence, q = _modelled(obs, layout, list(results), cands, alpha)
    white = whitening(obs, final.residuals, final.use, alpha)
    if white is not None:   # the noise differs between rates or axes, or is correlated: everything again, whitened
        obs = replace(obs, whitening=white)
        final, clip, evidence, q = _modelled(obs, layout, list(results), cands, alpha)
    if phases is not None and absorbed:  # reconstructed angles: their phases' uncertainty in every covariance
        final = with_phases_free(final, phases["segment"].to_numpy())
    # an offset step against the catalogue effect it holds, then offset effects against the offsets' measured
    # wander (``step_exchange``, ``wander``)
    offsets = OffsetNoise.from_fits(fits, random_walk)
    selected = final.active
    final, exchanged = step_or_effect(final, cands, offsets, alpha)
    final, wander = against_wander(final, offsets, alpha, output_unit)
    for name, text in exchanged.items():
        wander[name] = f"{text}; {wander[name]}" if name in wander else text
    # every extension against the noise's density at its signature's frequencies (``spectral``)
    final, spectral = against_spectrum(final, alpha)
    for name, text in spectral.items():
        wander[name] = f"{wander[name]}; {text}" if name in wander else text
    # the wander between segments in every uncertainty, and the extensions it leaves within them (``offset_wander``)
    final, widened = wander_tested(final, offsets, alpha)
    for name, text in widened.items():
        wander[name] = f"{wander[name]}; {text}" if name in wander else text
    # an offset effect set aside beside others that these stages then dropped, tried again (``offset_reentry``)
    final, back = taken_back(final, selected, offsets, alpha)
    for name, text in back.items():
        wander[name] = f"{wander[name]}; {text}" if name in wander else text

    rows, params, before = [], [], {}
    for effect in listed():   # one row per catalogue effect, in docs/effects.md's order
        if not effect.needs <= logged:   # the dataset lacks what it needs: not listed at all
            continue
        if isinstance(effect, LimitEffect):   # tested by its stuck samples, not by a model extension
            row, par = limit_rows(final, clip, evidence, q, alpha, dataset, output_unit, effect.name)
            if row["detected"]:
                unclipped = predict(obs, final.beta, layout, final.active, (None, None), final.structure)
                before[effect.name] = obs.y - unclipped
        else:
            row, par, reduced = catalogue_rows(final, cands, effect.name, alpha, dataset, output_unit,
                                               effect.name in absorbed, wander.get(effect.name))
            if reduced is not None:
                before[effect.name] = reduced.residuals
        rows.append(row)
        params += par
    step = step_row(final, dataset, output_unit)
    if step is not None:
        if STEP.effect in wander:   # what its test against the wander found
            step[0]["evidence"] += f"; {wander[STEP.effect]}"
        rows.append(step[0])
        before["unexplained: offset step"] = step[1].residuals
    res = _residuals(final, output_unit)
    recorded = replace(res, resid=final.residuals)   # the noise as recorded, which the fits' noise model describes
    a_u = config.unexplained_false_alarm
    # residuals at the numerical floor over every sample used (noise-free data): nothing beyond it is a finding
    rounding_rss = recorded.use.sum(axis=0) * final.obs.noise_floor**2
    for found in (tone_scan(recorded, a_u) + harmonic_scan(recorded, a_u) + segment_scan(recorded, a_u, SegmentNoise.from_fits(fits))
                  + static_step_scan(recorded, step_id, a_u, residual_autoregression(recorded))
                  + rate_dependence(final, a_u, output_unit, results)):
        if np.all(found.rss_reduction <= rounding_rss):  # what it removes is float rounding, not physics
            continue
        rows.append(scan_row(final, found, dataset))
    modelled = bool(final.active) or any(v is not None for v in clip)
    refined = refined_results(final, g_local, g_uncertainty) if modelled else ()
    findings = conform(pl.DataFrame(rows, schema=schema("diagnosis").polars_schema), "diagnosis")
    parameters = (conform(pl.DataFrame(params, schema=schema("effect_parameters").polars_schema), "effect_parameters")
                  if params else schema("effect_parameters").empty())
    return Diagnosis(findings, parameters, refined, final, before, n_all, phases)
