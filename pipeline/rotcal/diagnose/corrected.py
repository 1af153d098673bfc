"""The samples as the refined model sees them. The diagnosis's final model
writes each sample as the papers' model (per rate: offsets and
responsivities, Geist 2017 Eq. 1) plus the terms of the effects it modelled
(docs/effects.md, "The order of the forward model"); taking those terms
away, y - (model with them - model without them), leaves what the papers'
model with the refined parameters describes. Fitted segment by segment,
such samples give the per-segment estimates the consistency checks and the
offsets' change with rate use, under the refined model rather than biased
by the effects (a channel delay otherwise reads as an angle change with
rate). A clipped sample becomes the unclipped model's value (plus the noise
it kept)."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.diagnose import Diagnosis
from rotcal.diagnose.model import Structure, predict
from rotcal.diagnose.observed import observations
from rotcal.diagnose.reconstructed import with_reconstructed_angles
from rotcal.fit.segments import segment_rows
from rotcal.model.physics import CHANNELS


def without_effects(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame,
                    diagnosis: Diagnosis) -> pl.DataFrame:
    """``samples`` less the modelled effects' contribution (every sample of
    the diagnosed segments, none thinned; the others unchanged)."""
    final = diagnosis.final
    if final.obs.n == diagnosis.samples_available:  # none thinned: the diagnosis's observations are these samples
        obs = final.obs
    else:
        angled = samples  # the model's samples: with the reconstructed angles where the diagnosis had them
        if diagnosis.phases is not None and diagnosis.phases.height:
            angled, segments = with_reconstructed_angles(samples, segments, diagnosis.phases)
        built = observations(angled, segments, fits, final.obs.rates.tolist(), final.obs.g_local, samples.height)
        if built is None:
            return samples
        obs = built[0]
    # the final fit's own predictions where they are those of its parameters on these samples
    with_them = (final.ev.pred if obs is final.obs and final.converged
                 else predict(obs, final.beta, final.layout, final.active, final.clip, final.structure))
    effect = with_them - predict(obs, final.beta, final.layout, (), (None, None), Structure())
    # observations orders rows by (rate, time); each segment's rows stay in time order, as in ``samples``
    rows = segment_rows(samples)
    sample_rows = np.concatenate([rows[s][0] + np.arange(rows[s][1]) for s in np.unique(obs.segment)])
    y = samples.select(CHANNELS).to_numpy().copy()
    y[sample_rows] -= effect[np.argsort(obs.segment, kind="stable")]
    return samples.with_columns(pl.Series(c, y[:, i]) for i, c in enumerate(CHANNELS))

