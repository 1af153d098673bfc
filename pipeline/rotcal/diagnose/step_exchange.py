"""An offset step weighed against the catalogue effect it contains, under
the offsets' wander.

On a plan that takes the table axes in turn, an offset step between two
axes' segments holds the shift an ``axis_tilt`` gives its axis's segments
in the channel along that axis (the offsets are per rate, so a shift of
the first axis's segments is a step after them). The step has a size in
every channel, and under a wander of the sensor's bias its other channels'
sizes take the wander's own change across the step: against the whitened
samples, which leave the wander between segments out, they look
significant (a few tenths of a count at a tenth's uncertainty) and BIC
prefers the step over the one-parameter tilt (three of eight tilted
datasets under the mixed noise of ``scripts/noise_coverage.py``).

So, where the fits measured a wander, a selected step is exchanged for
each catalogue effect that moves segments' offsets, one at a time, and
the segment means of the exchanged model's residuals are tested for what
the step adds beyond that effect, with the wander refitted under both
hypotheses (``wander.segment_test``, as the step's own test, Bonferroni
over the segment boundaries its time could take). Where the wander
explains what the step adds, the effect that explains most of the rest
(least BIC) replaces it; the effect then faces the wander's test as every
selected one does.
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.candidates import STEP
from rotcal.diagnose.fitting import ModelFit, chi2_sf, fit_model
from rotcal.diagnose.model import Structure
from rotcal.diagnose.scans import p_is
from rotcal.diagnose.wander import OffsetNoise, offset_slopes, segment_test
from rotcal.model.effects import catalogue
from rotcal.model.effects.base import Candidate


def step_or_effect(final: ModelFit, candidates: tuple[Candidate, ...], noise: OffsetNoise,
                   alpha: float) -> tuple[ModelFit, dict[str, str]]:
    """The model with its offset step replaced by the catalogue effect that,
    with the wander, explains the step's pattern (module docstring), and the
    sentence that effect's row adds (none where nothing changed)."""
    if STEP not in final.active or not noise.wanders:
        return final, {}
    movers = {e.name for e in catalogue() if e.moves_segment_offsets}
    others = tuple(c for c in final.active if c != STEP)
    scanned = max(1, len(np.unique(final.obs.segment)) - 1)
    best: tuple[float, ModelFit, Candidate, float, float] | None = None
    for cand in candidates:
        if cand.effect not in movers or cand in final.active:
            continue
        trial = fit_model(final.obs, final.layout, final.beta, others + (cand,), final.clip, Structure(), final.use)
        test = segment_test(final, trial, STEP, noise, offset_slopes(trial, movers))
        if test is None:
            continue
        stat = test.stat
        p = min(1.0, chi2_sf(stat, len(STEP.names)) * scanned)
        if p >= alpha and (best is None or trial.bic < best[0]):
            best = (trial.bic, trial, cand, stat, p)
    if best is None:
        return final, {}
    _, trial, cand, stat, p = best
    return trial, {cand.effect: f"an offset step exchanged for {cand.key}: the offsets' wander explains what the step adds to it "
                   f"(chi-square {stat:.1f} on {len(STEP.names)} against the wander, {p_is(p)})"}
