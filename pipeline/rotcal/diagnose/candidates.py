"""The model extensions the diagnosis can add: every effect of the catalogue
(``rotcal.model.effects``) at its physical granularity (per rotation axis,
per channel, or for the whole dataset), and the generic structure rotcal
reports as ``unexplained`` (an offset step).

Internal parameters are chosen by each effect so that its extension is
smooth at zero (ripple as (a cos p, a sin p) rather than (a, p)); its
``report`` turns them into the parameters docs/effects.md names, with
uncertainties.
"""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects import Effects, catalogue, effect_named
from rotcal.model.effects.base import Candidate, ReportedParameter, scope_rank

STEP = Candidate("unexplained", "step", tuple(f"step_{c}" for c in CHANNELS), ((0,), (1,), (2,)))


def extensions(rotating_axes: tuple[str, ...], all_axes: tuple[str, ...], angles_measured: bool,
               logged: frozenset[str] = frozenset()) -> tuple[Candidate, ...]:
    """Every catalogue extension testable on a dataset with these segments
    and these ``logged`` per-sample observations (an effect's ``needs``), in
    the order of the model's parameters (each effect's ``slot``)."""
    cands = [(e, c) for e in catalogue() if e.needs <= logged
             for c in e.candidates(rotating_axes, all_axes, angles_measured)]
    return tuple(c for _, c in sorted(cands, key=lambda ec: (ec[0].slot, scope_rank(ec[1].scope), ec[0].listed)))


def effects_from(values: dict[str, float], clip: tuple[float | None, float | None]) -> Effects:
    """The forward model's effects from internal parameter values (missing:
    not modelled) and the clip limits."""
    given = {**values, "clip_low": clip[0], "clip_high": clip[1]}
    states = {e.name: e.state_from(given) for e in catalogue()}
    return Effects({name: state for name, state in states.items() if state is not None})


def report_parameters(cand: Candidate, value: np.ndarray, cov: np.ndarray, output_unit: str) -> list[ReportedParameter]:
    """The docs/effects.md parameters of a fitted extension, by first-order propagation."""
    return effect_named(cand.effect).report(cand, value, cov, output_unit)
