"""``cubic_nonlinearity``: cubic gain error (Pedley AN4399 Sec. 8):
y -> y (1 + k3 (y / x1g)^2) per channel."""

from __future__ import annotations

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Parameter
from rotcal.model.effects.families import PowerGainEffect


class CubicNonlinearity(PowerGainEffect):
    name = "cubic_nonlinearity"
    physics = "cubic gain error (Pedley AN4399 Sec. 8): y -> y (1 + k3 (y / x1g)^2)"
    parameters = tuple(Parameter(f"k3_{c}", "1", f"cubic coefficient of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (3e-4, 1.2e-3)
    size_of = "abs(k3) on one channel"
    where = "channel {s}, all segments"
    listed = 1
    slot = 1
    prefix = "k3"
    power = 2
    at_rest = "pose"
    at_rest_steps = {"k3": 1e-4}

    def chain(self, k, S, P, u):
        return S + (S + 2 * P) * k * u**2   # S f + P u f', with f = 1 + k u^2


EFFECT = CubicNonlinearity()
