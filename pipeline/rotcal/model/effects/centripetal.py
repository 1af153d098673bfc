"""``centripetal``: the sensing point sits at d from the rotation axis (d
perpendicular to it); the platter's centripetal acceleration -w^2 d adds to
the specific force (Gaitan 2021 Sec. 4): a -> a - w^2 d on rotation
segments, constant in the DUT frame, so each channel's offset grows with
w^2. Per rotation axis."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import AXES, axis_index
from rotcal.model.effects.base import (
    ALL,
    Candidate,
    Channel,
    ColumnContext,
    ForceEffect,
    Parameter,
    ReportedParameter,
    Support,
    on_runs,
)


def across(axis: str) -> tuple[str, str]:
    """The two table axes perpendicular to ``axis``."""
    a, b = (s for s in AXES if s != axis)
    return a, b


class Centripetal(ForceEffect):
    name = "centripetal"
    moves_segment_offsets = True
    physics = "the DUT sits at d off the rotation axis: a -> a - w^2 d (Gaitan 2021 Sec. 4)"
    parameters = (Parameter("radius_m", "m", "distance from the axis, abs(d)"), Parameter("d_x_m", "m", "component x of d"),
                  Parameter("d_y_m", "m", "component y of d"), Parameter("d_z_m", "m", "component z of d"))
    options = frozenset({"axis", "radius_m", "d_x_m", "d_y_m", "d_z_m"})
    magnitudes = frozenset({"radius_m"})
    sizes = (0.03, 0.25)
    size_of = "radius_m on one axis"
    where = "axis {s} rotation segments"
    listed = 0
    slot = 0

    def complete(self, params, rng):
        """A ``radius_m`` becomes d at a random angle across the axis."""
        out = super().complete(params, rng)
        axis = self.need_axis(out)
        a, b = across(axis)
        if "radius_m" in params:
            angle = rng.uniform(0, 2 * np.pi)
            out.update({f"d_{a}_m": params["radius_m"] * np.cos(angle), f"d_{b}_m": params["radius_m"] * np.sin(angle)})
        out.pop(f"d_{axis}_m", None)
        out["radius_m"] = float(np.hypot(out.get(f"d_{a}_m", 0.0), out.get(f"d_{b}_m", 0.0)))
        return out

    def state(self, previous, params):
        return {**(previous or {}), axis_index(params["axis"]): np.asarray([params.get(f"d_{s}_m", 0.0) for s in AXES], float)}

    def force(self, state, motion, a, g_local, rate_factor) -> None:
        for ax, d in state.items():
            on = motion.rotating & (motion.axis_idx == ax)
            omega = 2 * np.pi * motion.rate_hz[on] * rate_factor
            a[on] -= (omega**2)[:, None] * d[None, :]

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"centripetal:axis={axis},radius_m={size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, s, tuple(f"centripetal.{s}.d_{c}_m" for c in across(s)), (ALL, ALL))
                     for s in rotating_axes)

    def state_from(self, values):
        state = {}
        for s in AXES:
            a, b = across(s)
            if f"centripetal.{s}.d_{a}_m" in values:
                d = np.zeros(3)
                d[AXES.index(a)] = float(values[f"centripetal.{s}.d_{a}_m"])
                d[AXES.index(b)] = float(values[f"centripetal.{s}.d_{b}_m"])
                state[axis_index(s)] = d
        return state or None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d output / d d_j = -w^2 R_j / g on the axis's rotation samples."""
        a = AXES.index(cand.scope)
        j = AXES.index(name.split(".")[-1][2])  # centripetal.x.d_y_m -> component y
        m = ctx.motion
        factor = ctx.cached(("centripetal", a), lambda: np.where(
            m.rotating & ctx.on_axis[a], -(2 * np.pi * m.rate_hz * ctx.effects.rate_factor()) ** 2 / ctx.g_local, 0.0))
        runs = ctx.runs(self.support(cand))
        column = st.responsivity_times(j, st.slope, out, runs)
        return on_runs(runs, column, factor, out=column)

    def support(self, cand):
        return Support(AXES.index(cand.scope), rotating=True)

    def report(self, cand, value, cov, output_unit):
        radius = float(np.hypot(*value))
        grad = value / radius if radius > 0 else np.zeros(2)
        u = np.sqrt(np.diag(cov))
        return [ReportedParameter("radius_m", radius, float(np.sqrt(grad @ cov @ grad)), "m")] + [
            ReportedParameter(n.split(".")[-1], float(v), float(s), "m") for n, v, s in zip(cand.names, value, u)]


EFFECT = Centripetal()
