"""Offset effects taken back once the patterns that hid them are gone.

The wander test (``wander``) tests each selected offset effect with the
other selected ones free, so where two of them share a pattern in the
segments' offsets (a drift, and tilts of the axes recorded first and
last) neither has evidence of its own, and the one tested first is set
aside. The later stages (``spectral``, ``offset_wander``) may then drop
the other, and the pattern is left to the residuals, where the segment
misfit test names it ``unexplained`` (a drift of 0.019 counts/s under the
mixed noise of ``scripts/noise_coverage.py``, seed 2800: set aside at
chi-square 3.5 beside two tilts that were later found within noise).

So each offset effect the stages after the selection set aside is tried
again against the final model, as stepwise regression lets a variable
re-enter (Efroymson 1960): refitted into it, its pattern tested against
the wander with the final model's offset effects free
(``wander.segment_test``, Bonferroni over the offset patterns the
selection scored), and kept where that is significant at the diagnosis's
false-alarm rate and it passes the spectrum's test
(``spectral.against_spectrum``) and the Wald test under the wander between
segments (``offset_wander.with_offset_wander``). The most significant
first, one at a time.
"""

from __future__ import annotations

from rotcal.diagnose.fitting import ModelFit, chi2_sf, fit_model
from rotcal.diagnose.offset_wander import wald_test, with_offset_wander
from rotcal.diagnose.scans import p_is
from rotcal.diagnose.spectral import against_spectrum
from rotcal.diagnose.wander import SEGMENT_CONSTANT, OffsetNoise, offset_slopes, segment_test
from rotcal.model.effects import catalogue
from rotcal.model.effects.base import Candidate


def taken_back(final: ModelFit, set_aside: tuple[Candidate, ...], noise: OffsetNoise, alpha: float
               ) -> tuple[ModelFit, dict[str, str]]:
    """``final`` with the offset effects of ``set_aside`` that its own
    offset effects no longer hide (module docstring), and per effect the
    sentence its row adds."""
    texts: dict[str, str] = {}
    rivals = {e.name for e in catalogue() if e.moves_segment_offsets}
    scanned = max(1, sum(c.effect in rivals for c in final.layout.candidates))
    remaining = [c for c in set_aside if c.effect in rivals and c not in final.active]
    while remaining and noise.wanders:
        tried = []
        for cand in remaining:
            trial = fit_model(final.obs, final.layout, final.beta, final.active + (cand,), final.clip,
                              final.structure, final.use)
            test = segment_test(trial, final, cand, noise, offset_slopes(trial, rivals))
            if test is None or test.constant < SEGMENT_CONSTANT:
                continue
            p = min(1.0, chi2_sf(test.stat, len(cand.names)) * scanned)
            if p < alpha:
                tried.append((p, cand.key, cand, trial, test.stat))
        taken = None
        for p, _, cand, trial, stat in sorted(tried, key=lambda t: t[:2]):
            kept, _ = against_spectrum(trial, alpha, (cand,))
            if cand not in kept.active:
                continue
            widened = with_offset_wander(kept, noise)
            wald, p_wald = wald_test(widened, cand)
            if p_wald < alpha:
                taken = (cand, widened, p, stat, wald)
                break
        if taken is None:
            break
        cand, final, p, stat, wald = taken
        remaining.remove(cand)
        text = (f"{cand.key} taken back: with the final model's offset effects free, the evidence favours it over "
                f"the offsets' wander (chi-square {stat:.1f} on {len(cand.names)} against the wander, {p_is(p)}; "
                f"Wald chi-square {wald:.1f} with the wander between segments in its uncertainty)")
        texts[cand.effect] = f"{texts[cand.effect]}; {text}" if cand.effect in texts else text
    return final, texts
