"""``rate_ripple``: the rotation is not uniform, a once-per-revolution speed
ripple: theta -> theta + a sin(theta + p), per rotation axis.

The diagnosis fits (a cos p, a sin p), smooth at zero, and reports a and p.
"""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import AXES, axis_index
from rotcal.model.effects.base import (
    ALL,
    AngleEffect,
    Candidate,
    Channel,
    ColumnContext,
    Parameter,
    ReportedParameter,
    Support,
    on_runs,
)


class RateRipple(AngleEffect):
    name = "rate_ripple"
    physics = "once-per-revolution speed ripple: theta -> theta + a sin(theta + p)"
    parameters = (Parameter("ripple_deg", "degree", "amplitude a"), Parameter("ripple_phase_deg", "degree", "phase p"))
    options = frozenset({"axis", "ripple_deg", "ripple_phase_deg"})
    sizes_given = frozenset({"ripple_deg"})
    magnitudes = frozenset({"ripple_deg"})
    sizes = (0.03, 0.2)
    size_of = "ripple_deg"
    where = "axis {s} rotation segments"
    listed = 6
    slot = 4

    def complete(self, params, rng):
        out = super().complete(params, rng)
        self.need_axis(out)
        out.setdefault("ripple_phase_deg", rng.uniform(0, 360))
        return out

    def state(self, previous, params):
        return {**(previous or {}), axis_index(params["axis"]): np.asarray((params.get("ripple_deg", 0.0), params["ripple_phase_deg"]), float)}

    def angle(self, state, motion, base):
        ripple = np.zeros_like(base)
        for ax, (amp, phase) in state.items():
            on = motion.axis_idx[motion.rotating] == ax
            ripple[on] = amp * np.sin(np.deg2rad(base[on] + phase))
        return ripple

    def angle_slope(self, state, motion, base):
        slope = np.zeros_like(base)
        for ax, (amp, phase) in state.items():
            on = motion.axis_idx[motion.rotating] == ax
            slope[on] = np.deg2rad(amp) * np.cos(np.deg2rad(base[on] + phase))
        return slope

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"rate_ripple:axis={axis},ripple_deg={size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        if angles_measured:
            return ()
        return tuple(Candidate(self.name, s, (f"ripple.{s}.a_deg", f"ripple.{s}.b_deg"), (ALL, ALL)) for s in rotating_axes)

    def state_from(self, values):
        state = {}
        for s in AXES:
            if f"ripple.{s}.a_deg" in values:
                alpha, beta = float(values[f"ripple.{s}.a_deg"]), float(values[f"ripple.{s}.b_deg"])
                state[axis_index(s)] = np.asarray((float(np.hypot(alpha, beta)), float(np.degrees(np.arctan2(beta, alpha)))), float)
        return state or None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d theta / d(a cos p) = sin(base), d theta / d(a sin p) = cos(base)."""
        a, delay = AXES.index(cand.scope), ctx.effects.delays()[st.r]

        def make() -> np.ndarray:   # (sin, cos) of the base angle on the axis's rotation samples: both columns' at once
            waves = np.zeros((2, ctx.motion.t_s.size))
            idx = np.flatnonzero(ctx.motion.rotating)
            sel = ctx.on_axis[a][idx]
            base = np.deg2rad(st.base[sel])
            waves[0, idx[sel]] = np.sin(base)
            waves[1, idx[sel]] = np.cos(base)
            return waves
        wave = ctx.cached(("ripple", a, delay), make)[0 if name.endswith(".a_deg") else 1]
        return on_runs(ctx.runs(self.support(cand)), st.d_theta, wave, out=out)

    def support(self, cand):
        return Support(AXES.index(cand.scope), rotating=True)

    def report(self, cand, value, cov, output_unit):
        alpha, beta = value
        amp = float(np.hypot(alpha, beta))
        g_amp = np.array([alpha, beta]) / amp if amp > 0 else np.zeros(2)
        g_phase = np.degrees(np.array([-beta, alpha]) / max(amp**2, 1e-300))
        return [
            ReportedParameter("ripple_deg", amp, float(np.sqrt(g_amp @ cov @ g_amp)), "degree"),
            ReportedParameter("ripple_phase_deg", float(np.degrees(np.arctan2(beta, alpha)) % 360.0),
                              float(np.sqrt(g_phase @ cov @ g_phase)), "degree"),
        ]


EFFECT = RateRipple()
