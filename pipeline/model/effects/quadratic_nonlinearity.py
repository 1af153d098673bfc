"""``quadratic_nonlinearity``: even-order gain error:
y -> y (1 + k2 (y / x1g)) per channel."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, GainEffect, Parameter


class QuadraticNonlinearity(GainEffect):
    name = "quadratic_nonlinearity"
    physics = "even-order gain error: y -> y (1 + k2 (y / x1g))"
    parameters = tuple(Parameter(f"k2_{c}", "1", f"quadratic coefficient of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (2e-4, 8e-4)
    size_of = "abs(k2) on one channel"
    where = "channel {s}, all segments"
    listed = 2
    slot = 1

    def state(self, previous, params):
        k = np.zeros(3) if previous is None else np.array(previous)
        for r, c in enumerate(CHANNELS):
            k[r] = params.get(f"k2_{c}", k[r])
        return k

    def gain(self, k, u):
        return 1.0 + k * u

    def chain(self, k, S, P, u):
        return S * (1 + k * u) + P * k * u   # S f + P u f', with f = 1 + k u

    def gain_derivative(self, u):
        return u

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"quadratic_nonlinearity:k2_{channel}={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, c, (f"k2_{c}",), ((r,),)) for r, c in enumerate(CHANNELS))

    def state_from(self, values):
        names = [f"k2_{c}" for c in CHANNELS]
        return np.array([float(values.get(n, 0.0)) for n in names]) if any(n in values for n in names) else None


EFFECT = QuadraticNonlinearity()
