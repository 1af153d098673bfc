"""The diagnosis tables: one row per catalogue effect (detected or not) and
per unexplained finding, each with the numbers of the model it tested, and
the parameters of every detected effect."""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.candidates import STEP, report_parameters
from rotcal.diagnose.clipping import StuckValue
from rotcal.diagnose.fitting import ModelFit, bic, chi2_sf, score, without
from rotcal.diagnose.model import predict
from rotcal.diagnose.scans import Unexplained, counted, p_is
from rotcal.model.effects import effect_named
from rotcal.model.effects.base import Candidate
from rotcal.model.physics import AXES


def _where(cands: list[Candidate]) -> str:
    return "; ".join(effect_named(c.effect).where.format(s=c.scope) for c in cands)


def _param_text(params) -> str:
    return ", ".join(f"{p.name} = {p.value:.4g} ± {p.std_uncertainty:.2g}" for p in params)


def _row(dataset, effect, detected, where, evidence, before, after, dbic, p) -> dict:
    return {"dataset": dataset, "effect": effect, "detected": detected, "where": where, "evidence": evidence,
            "rms_before": before, "rms_after": after, "delta_bic": dbic, "p_value": p}


def catalogue_rows(final: ModelFit, candidates: tuple[Candidate, ...], effect: str, alpha: float,
                   dataset: str, output_unit: str, absorbed: bool = False,
                   wander: str | None = None) -> tuple[dict, list[dict], ModelFit | None]:
    """The diagnosis row of one catalogue effect and, if detected, its
    parameters and the model refitted without it (the "before");
    ``absorbed``: the reconstructed table angles absorb it (not tested);
    ``wander``: what its test against the offsets' wander found (``wander``)."""
    granules = [c for c in candidates if c.effect == effect]
    found = [c for c in final.active if c.effect == effect]
    if absorbed:
        return _row(dataset, effect, False, "not testable here", "the table angles are reconstructed from the "
                    "segments' fitted phases and rates, which absorb it", final.rms, final.rms, 0.0, 1.0), [], None
    if not granules:
        return _row(dataset, effect, False, "not testable here", "the dataset has no segments this effect acts on",
                    final.rms, final.rms, 0.0, 1.0), [], None
    if not found:
        s = score(final, tuple(granules))
        singles = sorted((score(final, (c,)).p_value, c.key) for c in granules)
        rms_after = float(np.sqrt(s.rss.sum() / final.n_total))
        if wander is not None:
            return _row(dataset, effect, False, "tested: " + _where(granules), f"not detected: {wander}", final.rms,
                        rms_after, s.delta_bic, singles[0][0]), [], None
        evidence = (f"not detected: modelling it everywhere it could act lowers chi-square by {s.chi2:.1f} on "
                    f"{counted(sum(len(c.names) for c in granules), 'parameter')} (BIC change {s.delta_bic:+.1f}); the strongest "
                    f"single test ({singles[0][1]}) has {p_is(singles[0][0])}, above the false-alarm rate {alpha:g}")
        return _row(dataset, effect, False, "tested: " + _where(granules), evidence, final.rms, rms_after,
                    s.delta_bic, singles[0][0]), [], None
    reduced = without(final, tuple(found))
    lr = float(np.sum(final.ev.n_used * np.log(reduced.ev.rss / final.ev.rss)))
    k = sum(len(c.names) for c in found)
    p = chi2_sf(lr, k)
    params, rows = [], []
    for c in found:
        value, cov = final.param_block(c)
        reported = report_parameters(c, value, cov, output_unit)
        params += reported
        axis = c.scope if c.scope in AXES else ""
        rows += [{"dataset": dataset, "effect": effect, "axis": axis, "parameter": q.name, "value": q.value,
                  "std_uncertainty": q.std_uncertainty, "unit": q.unit} for q in reported]
    rivals = [score(reduced, (c,)) for c in candidates if c.effect != effect and c not in reduced.active]
    rival = min(rivals, key=lambda s: s.delta_bic) if rivals else None
    own = final.bic - reduced.bic
    versus = (f"; the best other explanation, {rival.candidate.key}, would change BIC by {rival.delta_bic:+.0f}"
              if rival is not None else "")
    evidence = (f"modelling it lowers chi-square by {lr:.0f} on {counted(k, 'parameter')} ({p_is(p)}, BIC change "
                f"{own:+.0f}); {_param_text(params)}{versus}{'; ' + wander if wander else ''}")
    return _row(dataset, effect, True, _where(found), evidence, reduced.rms, final.rms, own, p), rows, reduced


def limit_rows(final: ModelFit, clip, evidence: list[StuckValue], q: float, alpha: float,
                  dataset: str, output_unit: str, effect: str) -> tuple[dict, list[dict]]:
    """The row of a limit ``effect`` (clipping): the model with and without
    the limits, on every sample."""
    obs = final.obs
    k = sum(v is not None for v in clip)
    clipped = obs.whitened(obs.y - final.ev.pred)
    unclipped = (obs.whitened(obs.y - predict(obs, final.beta, final.layout, final.active, (None, None), final.structure))
                 if k else clipped)
    n = np.full(3, obs.n)
    rss_before, rss_after = (unclipped**2).sum(axis=0), (clipped**2).sum(axis=0)
    dbic = bic(rss_after, n, k, 3 * obs.n, obs.noise_floor) - bic(rss_before, n, 0, 3 * obs.n, obs.noise_floor)
    rms = lambda rss: float(np.sqrt(rss.sum() / (3 * obs.n)))  # noqa: E731
    strongest = min(evidence, key=lambda e: e.p_value)
    p = min(1.0, strongest.p_value * len(evidence))
    if not k:
        return _row(dataset, effect, False, "tested: every channel's extremes",
                    f"not detected: no extreme value is repeated beyond chance (largest run {counted(strongest.count, 'sample')} at "
                    f"{strongest.value:g} in channel {strongest.channel}; {p_is(p)})",
                    rms(rss_before), rms(rss_before), float(k * np.log(3 * obs.n)), p), []
    params, where, detail = [], [], []
    for side, limit in zip(("low", "high"), clip):
        if limit is None:
            continue
        hits = [e for e in evidence if e.side == side and e.value == limit]
        share = sum(e.count for e in hits) / (3 * obs.n)
        where.append(f"channels {', '.join(e.channel for e in hits)} at {limit:g} {output_unit} ({100 * share:.2g} % of samples)")
        detail.append(", ".join(f"{e.count} samples of {e.channel} at {limit:g} against {e.neighbour_count} one step inside"
                                for e in hits))
        params.append({"dataset": dataset, "effect": effect, "axis": "", "parameter": f"clip_{side}",
                       "value": limit, "std_uncertainty": q, "unit": output_unit})
    evidence_text = (f"runs of samples stuck at the extremes: {'; '.join(detail)} ({p_is(p)}: binomial against the "
                     f"neighbouring value or censoring against the model); "
                     f"samples the limit can have touched are left out of every fit")
    return _row(dataset, effect, True, "; ".join(where), evidence_text, rms(rss_before), rms(rss_after), dbic, p), params


def step_row(final: ModelFit, dataset: str, output_unit: str) -> tuple[dict, ModelFit] | None:
    if STEP not in final.active:
        return None
    reduced = without(final, (STEP,))
    value, cov = final.param_block(STEP)
    u = np.sqrt(np.diag(cov))
    t = final.structure.step_t_s
    seg = final.obs.segment[np.argmin(np.abs(final.obs.motion.t_s - t))]
    amps = ", ".join(f"{v:+.1f} ± {e:.1f}" for v, e in zip(value, u))
    evidence = (f"step of {amps} {output_unit} in channels u, v, w at t = {t:.1f} s; "
                f"modelling it changes BIC by {final.bic - reduced.bic:+.0f}; no catalogue effect explains it better")
    return _row(dataset, "unexplained", True, f"all channels at t = {t:.1f} s (near segment {seg})", evidence,
                reduced.rms, final.rms, final.bic - reduced.bic, 0.0), reduced


def scan_row(final: ModelFit, found: Unexplained, dataset: str) -> dict:
    rss_after = np.maximum(final.ev.rss - found.rss_reduction, 1e-300)
    dbic = bic(rss_after, final.ev.n_used, final.n_params + found.n_params, final.n_total, final.obs.noise_floor) - final.bic
    return _row(dataset, "unexplained", True, found.where, found.evidence, final.rms,
                float(np.sqrt(rss_after.sum() / final.n_total)), dbic, found.p_value)
