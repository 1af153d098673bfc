"""``offset_drift``: offsets drift during the recording (warm-up):
O_r -> O_r + rho_r (t - t0), t0 the dataset's first sample time."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, Channel, ColumnContext, OffsetEffect, Parameter
from rotcal.model.effects.families import PerChannelEffect


class OffsetDrift(PerChannelEffect, OffsetEffect):
    name = "offset_drift"
    physics = "offsets drift during the recording: O_r -> O_r + rho_r (t - t0)"
    parameters = tuple(Parameter(f"drift_{c}", "output unit per s", f"drift rho of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (0.006, 0.03)
    size_of = "abs(rho) on one channel, bit per s"
    where = "channel {s}, whole recording"
    listed = 8
    slot = 1
    prefix = "drift"
    at_rest = "time"
    at_rest_steps = {"drift": 1e-3}

    def state(self, previous, params):
        # a later request replaces the drifts (the catalogue's other per-channel effects fill in)
        return np.asarray([params.get(f"drift_{c}", 0.0) for c in CHANNELS], float)

    def offset(self, state, motion):
        return np.asarray(state)[None, :] * (motion.t_s - motion.t0_s)[:, None]

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        return ctx.cached("drift", lambda: ctx.motion.t_s - ctx.motion.t0_s)


EFFECT = OffsetDrift()
