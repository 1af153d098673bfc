"""The phases of rotations without a table angle, solved jointly with the
effects the diagnosis models.

The phase-free reduction solves each segment's phase offset theta_k from
the segments' fitted coefficients (``rotcal.combine.phasefree``), and an
effect that turns a channel's phase (``channel_delay``: 360 f tau) or moves
the offsets biases that solution. The diagnosis holds the reconstructed
angles fixed, so its effect parameters would absorb part of the bias. The
joint solution is the fixed point of the map theta -> (diagnose with theta;
refit the segments on the samples less the modelled effects; solve the
phases again). That map contracts slowly where the effect and the phases
are strongly correlated (a factor of about 0.75 per step for a channel
delay), so its fixed point is found by Anderson acceleration (Walker & Ni
2011, SIAM J. Numer. Anal. 49, 1715; type II, the last ``MEMORY`` steps).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

import numpy as np
import polars as pl

from rotcal.combine.unreferenced import segment_phases
from rotcal.diagnose import Diagnosis
from rotcal.diagnose.corrected import without_effects
from rotcal.fit.segments import fits_frame, segment_rows
from rotcal.fit.sinefit import fit_sine
from rotcal.model.physics import CHANNELS

MEMORY = 4           # Anderson acceleration: previous steps kept
MAX_STEPS = 8        # diagnoses at most per dataset
TOLERANCE = 0.2      # stop when every phase moves by less than this fraction of its standard uncertainty


def phases_without_effects(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame, diagnosis: Diagnosis,
                           *, own_phase: frozenset[int], g_local: float, g_uncertainty: float,
                           clock_factor: float) -> pl.DataFrame:
    """The reconstructed segments' phases solved again from the samples less
    the modelled effects: each own-phase segment refitted against its own
    phase (``rotcal.fit.sinefit``, from its previous rate) and the phase-free
    solution repeated (``rotcal.combine.unreferenced.segment_phases``). The
    effects bias the first solution's theta_k, which the diagnosis holds
    fixed; this removes the part of the bias its model explains."""
    assert diagnosis.phases is not None
    clean = without_effects(samples, segments, fits, diagnosis)
    rows = segment_rows(clean)
    t_ns, y = clean["t_ns"].to_numpy(), clean.select(CHANNELS).to_numpy()
    refits = []
    for k, rate in diagnosis.phases.select("segment", "phase_rate_hz").iter_rows():
        a, n = rows[k]
        fit = fit_sine(t_ns[a : a + n], y[a : a + n], rate, search=False)
        refits.append(replace(fit.fit, segment=k, rate_fit_hz=fit.rate_hz * clock_factor))
    again = pl.concat([fits.filter(~pl.col("segment").is_in(diagnosis.phases["segment"].implode())),
                       fits_frame(refits, segments, fits["dataset"][0])])
    return segment_phases(again, segments, own_phase, g_local, g_uncertainty, clock_factor)


def _wrapped(delta_deg: np.ndarray) -> np.ndarray:
    return (delta_deg + 180.0) % 360.0 - 180.0


def jointly_diagnosed(diagnose_with: Callable[[pl.DataFrame], Diagnosis | None],
                      refit: Callable[[Diagnosis], pl.DataFrame], phases: pl.DataFrame) -> Diagnosis | None:
    """The diagnosis at the fixed point of theta -> refit(diagnose_with(theta))
    (module docstring), starting from the phase-free ``phases``; the first
    diagnosis when it models nothing (the phases then have no effect to
    answer for)."""
    theta = phases["theta_k_deg"].to_numpy()
    tolerance = TOLERANCE * np.maximum(phases["theta_k_u_deg"].to_numpy(), 1e-12)
    steps: list[tuple[np.ndarray, np.ndarray]] = []   # (theta, F(theta) - theta)
    diagnosis = diagnose_with(phases)
    for _ in range(MAX_STEPS - 1):
        if diagnosis is None or not (diagnosis.final.active or diagnosis.before):
            return diagnosis
        mapped = refit(diagnosis)
        if not mapped["segment"].equals(phases["segment"]):  # a refit or a rate's solution failed: keep what there is
            return diagnosis
        change = _wrapped(mapped["theta_k_deg"].to_numpy() - theta)
        if np.all(np.abs(change) < tolerance):
            return diagnosis
        steps = (steps + [(theta, change)])[-MEMORY - 1 :]
        step = change
        if len(steps) > 1:   # Anderson (type II): the combination of the last steps whose change is least
            d_theta = np.column_stack([b[0] - a[0] for a, b in zip(steps, steps[1:])])
            d_change = np.column_stack([b[1] - a[1] for a, b in zip(steps, steps[1:])])
            gamma = np.linalg.lstsq(d_change, change, rcond=None)[0]
            step = change - (d_theta + d_change) @ gamma
        theta = theta + step
        phases = mapped.with_columns(theta_k_deg=pl.Series(theta % 360.0))
        diagnosis = diagnose_with(phases)
    return diagnosis
