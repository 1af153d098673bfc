"""``axis_tilt``: the rotation axis is not perpendicular to gravity (table
not level): a -> cos(tilt) a + g sin(tilt) s_hat, a constant component along
the axis s_hat and the rotating part shrunk by cos(tilt); per axis."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import AXES, axis_index
from rotcal.model.effects.base import (
    ALL,
    Candidate,
    Channel,
    ColumnContext,
    GravityEffect,
    Parameter,
    ReportedParameter,
    Support,
    on_runs,
)


class AxisTilt(GravityEffect):
    name = "axis_tilt"
    moves_segment_offsets = True
    physics = "the rotation axis is tilted from horizontal: a -> cos(tilt) a + g sin(tilt) s_hat"
    parameters = (Parameter("tilt_deg", "degree", "tilt, positive when gravity gains a component along +s_hat"),)
    options = frozenset({"axis", "tilt_deg"})
    sizes = (0.08, 0.5)
    size_of = "abs(tilt_deg) on one axis"
    where = "axis {s} segments (static and rotation)"
    listed = 7
    slot = 5

    def complete(self, params, rng):
        out = super().complete(params, rng)
        self.need_axis(out)
        return out

    def state(self, previous, params):
        return {**(previous or {}), axis_index(params["axis"]): np.asarray((params.get("tilt_deg", 0.0),), float)}

    def force(self, state, motion, a, g_local, rate_factor) -> None:
        for ax, (tilt_deg,) in state.items():
            on = motion.axis_idx == ax
            a[on] *= np.cos(np.deg2rad(tilt_deg))
            a[on, ax] += g_local * np.sin(np.deg2rad(tilt_deg))

    def angle_scale(self, state, motion):
        scale = np.ones(motion.t_s.size)
        for ax, (tilt_deg,) in state.items():
            scale[motion.axis_idx == ax] = np.cos(np.deg2rad(tilt_deg))
        return scale

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"axis_tilt:axis={axis},tilt_deg={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, s, (f"tilt.{s}_deg",), (ALL,)) for s in all_axes)

    def state_from(self, values):
        state = {axis_index(s): np.asarray((float(values[f"tilt.{s}_deg"]),), float) for s in AXES if f"tilt.{s}_deg" in values}
        return state or None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d a / d tilt = -sin(tilt) up + cos(tilt) s_hat (per degree), through r."""
        a, delay = AXES.index(cand.scope), ctx.effects.delays()[st.r]
        runs = ctx.runs(self.support(cand))

        def make() -> np.ndarray:   # per component, (3, n); on the axis's runs (slices, not a mask: 2.3x faster)
            tilt = np.deg2rad((ctx.effects.states.get(self.name) or {}).get(a, (0.0,))[0])
            d_a = np.zeros((3, ctx.motion.t_s.size))
            for _, at in runs:
                d_a[:, at] = -np.sin(tilt) * st.up[:, at] * (np.pi / 180.0)
                d_a[a, at] += np.cos(tilt) * (np.pi / 180.0)
            return d_a
        column = st.responsivity_dot(ctx.cached((name, delay), make), out, runs)
        return column if st.unit_slope else on_runs(runs, column, st.slope, out=column)

    def support(self, cand):
        return Support(AXES.index(cand.scope))

    def report(self, cand, value, cov, output_unit):
        # the model holds the tilt through its sine and cosine, so the fit may settle a whole turn away
        return [ReportedParameter("tilt_deg", float((value[0] + 180.0) % 360.0 - 180.0), float(np.sqrt(cov[0, 0])), "degree")]


EFFECT = AxisTilt()
