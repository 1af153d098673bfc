"""``offset_drift``: offsets drift during the recording (warm-up):
O_r -> O_r + rho_r (t - t0), t0 the dataset's first sample time."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, Channel, ColumnContext, OffsetEffect, Parameter


class OffsetDrift(OffsetEffect):
    name = "offset_drift"
    physics = "offsets drift during the recording: O_r -> O_r + rho_r (t - t0)"
    parameters = tuple(Parameter(f"drift_{c}", "output unit per s", f"drift rho of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (0.006, 0.03)
    size_of = "abs(rho) on one channel, bit per s"
    where = "channel {s}, whole recording"
    listed = 8
    slot = 1

    def state(self, previous, params):
        return np.asarray([params.get(f"drift_{c}", 0.0) for c in CHANNELS], float)

    def offset(self, state, motion):
        return np.asarray(state)[None, :] * (motion.t_s - motion.t0_s)[:, None]

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"offset_drift:drift_{channel}={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, c, (f"drift_{c}",), ((r,),)) for r, c in enumerate(CHANNELS))

    def state_from(self, values):
        names = [f"drift_{c}" for c in CHANNELS]
        return np.array([float(values.get(n, 0.0)) for n in names]) if any(n in values for n in names) else None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext) -> np.ndarray:
        return ctx.cached("drift", lambda: ctx.motion.t_s - ctx.motion.t0_s)


EFFECT = OffsetDrift()
