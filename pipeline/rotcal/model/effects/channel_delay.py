"""``channel_delay``: a channel is not sampled at the instant stamped
(sequential sampling, different filters): the sample of channel r stamped t
was taken at t + delay_r; delay_u = 0."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, Channel, ColumnContext, Parameter, SamplingEffect


class ChannelDelay(SamplingEffect):
    name = "channel_delay"
    physics = "a channel is sampled delay_r after its stamp (delay_u = 0)"
    parameters = (Parameter("delay_v_s", "s", "delay of v after u"), Parameter("delay_w_s", "s", "delay of w after u"))
    options = frozenset({"delay_v_s", "delay_w_s"})
    sizes = (0.5e-3, 6e-3)
    size_of = "each delay, on v and/or w"
    where = "channel {s}, rotation segments"
    listed = 4
    slot = 2

    def state(self, previous, params):
        return (0.0, params.get("delay_v_s", 0.0), params.get("delay_w_s", 0.0))

    def delays(self, state):
        return np.asarray(state, float)

    def draw(self, size, sign, axis, channel, rng) -> str:
        low, high = self.sizes
        which = rng.choice(("v", "w", "vw"))
        return "channel_delay:" + ",".join(f"delay_{c}_s={rng.uniform(low, high):.6g}" for c in which)

    def candidates(self, rotating_axes, all_axes, angles_measured):
        if not rotating_axes:
            return ()
        return tuple(Candidate(self.name, c, (f"delay_{c}_s",), ((r,),)) for r, c in enumerate(CHANNELS) if r > 0)

    def state_from(self, values):
        if "delay_v_s" not in values and "delay_w_s" not in values:
            return None
        return (0.0, float(values.get("delay_v_s", 0.0)), float(values.get("delay_w_s", 0.0)))

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d theta / d delay = the true rate, 360 rate (1 + e) degree per s."""
        m = ctx.motion
        rate = ctx.cached("delay", lambda: np.where(m.rotating, 360.0 * m.rate_hz * ctx.effects.rate_factor(), 0.0))
        return np.multiply(np.multiply(st.d_theta, st.stretch, out=out), rate, out=out)


EFFECT = ChannelDelay()
