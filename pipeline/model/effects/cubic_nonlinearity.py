"""``cubic_nonlinearity``: cubic gain error (Pedley AN4399 Sec. 8):
y -> y (1 + k3 (y / x1g)^2) per channel."""

from __future__ import annotations

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, GainEffect, Parameter


class CubicNonlinearity(GainEffect):
    name = "cubic_nonlinearity"
    physics = "cubic gain error (Pedley AN4399 Sec. 8): y -> y (1 + k3 (y / x1g)^2)"
    parameters = tuple(Parameter(f"k3_{c}", "1", f"cubic coefficient of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (3e-4, 1.2e-3)
    size_of = "abs(k3) on one channel"
    where = "channel {s}, all segments"
    listed = 1
    slot = 1

    def state(self, previous, params):
        k = np.zeros(3) if previous is None else np.array(previous)
        for r, c in enumerate(CHANNELS):
            k[r] = params.get(f"k3_{c}", k[r])
        return k

    def gain(self, k, u):
        return 1.0 + k * u**2

    def chain(self, k, S, P, u):
        return S + (S + 2 * P) * k * u**2   # S f + P u f', with f = 1 + k u^2

    def gain_derivative(self, u):
        return u**2

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"cubic_nonlinearity:k3_{channel}={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, c, (f"k3_{c}",), ((r,),)) for r, c in enumerate(CHANNELS))

    def state_from(self, values):
        names = [f"k3_{c}" for c in CHANNELS]
        return np.array([float(values.get(n, 0.0)) for n in names]) if any(n in values for n in names) else None


EFFECT = CubicNonlinearity()
