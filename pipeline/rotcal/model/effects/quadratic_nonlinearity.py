"""``quadratic_nonlinearity``: even-order gain error:
y -> y (1 + k2 (y / x1g)) per channel."""

from __future__ import annotations

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Parameter
from rotcal.model.effects.families import PowerGainEffect


class QuadraticNonlinearity(PowerGainEffect):
    name = "quadratic_nonlinearity"
    physics = "even-order gain error: y -> y (1 + k2 (y / x1g))"
    parameters = tuple(Parameter(f"k2_{c}", "1", f"quadratic coefficient of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (2e-4, 8e-4)
    size_of = "abs(k2) on one channel"
    where = "channel {s}, all segments"
    listed = 2
    slot = 1
    prefix = "k2"
    power = 1
    at_rest = "pose"
    at_rest_steps = {"k2": 1e-4}

    def chain(self, k, S, P, u):
        return S * (1 + k * u) + P * k * u   # S f + P u f', with f = 1 + k u


EFFECT = QuadraticNonlinearity()
