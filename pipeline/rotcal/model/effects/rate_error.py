"""``rate_error``: the true rotation rate differs from the commanded one
(stage rate error, logger clock drift): rate -> rate (1 + e) against the
commanded ``angle_deg``; rotation segments only."""

from __future__ import annotations

import numpy as np

from rotcal.model.effects.base import ALL, AngleEffect, Candidate, Channel, ColumnContext, Parameter


class RateError(AngleEffect):
    name = "rate_error"
    physics = "the true rotation rate differs from the commanded one: rate -> rate (1 + e)"
    parameters = (Parameter("rate_error", "1", "fractional rate error e"),)
    options = frozenset({"rate_error"})
    sizes = (5e-5, 4e-4)
    size_of = "abs(rate_error)"
    where = "all rotation segments"
    listed = 5
    slot = 3
    absorbed_by_own_phase = True

    def state(self, previous, params):
        return params.get("rate_error", 0.0)

    def rate_factor(self, state) -> float:
        return 1.0 + state

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"rate_error:rate_error={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        # measured angles (MCAP joint states) carry the true rate: nothing to fit
        return (Candidate(self.name, "", ("rate_error",), (ALL,)),) if rotating_axes and not angles_measured else ()

    def state_from(self, values):
        return float(values["rate_error"]) if "rate_error" in values else None

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        """d theta / d e = 360 rate (t + delay - t_start), through the ripple's stretch."""
        m, delay = ctx.motion, ctx.effects.delays()[st.r]
        rate = ctx.cached(("rate", delay), lambda: np.where(m.rotating, 360.0 * m.rate_hz * (m.t_s + delay - m.t_start_s), 0.0))
        return np.multiply(np.multiply(st.d_theta, st.stretch, out=out), rate, out=out)


EFFECT = RateError()
