"""Families of effects that share one implementation: a coefficient per
channel (``PerChannelEffect``: its state, simulator draw and diagnosis
candidates) and, of those, a gain error 1 + k u^power (``PowerGainEffect``)."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from rotcal.model.conventions import CHANNELS
from rotcal.model.effects.base import Candidate, Effect, GainEffect


class PerChannelEffect(Effect):
    """An effect with one coefficient per channel, ``{prefix}_u``, ``_v``,
    ``_w``: its state (a later request fills in the channels it names), its
    simulator draw and its diagnosis candidates (one per channel)."""

    prefix: ClassVar[str]

    def coefficient(self, channel: str) -> str:
        return f"{self.prefix}_{channel}"

    def state(self, previous: Any, params: dict) -> Any:
        k = np.zeros(3) if previous is None else np.array(previous)
        for r, c in enumerate(CHANNELS):
            k[r] = params.get(self.coefficient(c), k[r])
        return k

    def draw(self, size: float, sign: float, axis: str, channel: str, rng: np.random.Generator) -> str:
        return f"{self.name}:{self.coefficient(channel)}={sign * size:.6g}"

    def candidates(self, rotating_axes: tuple[str, ...], all_axes: tuple[str, ...],
                   angles_measured: bool) -> tuple[Candidate, ...]:
        return tuple(Candidate(self.name, c, (self.coefficient(c),), ((r,),)) for r, c in enumerate(CHANNELS))

    def state_from(self, values: dict[str, Any]) -> Any:
        names = [self.coefficient(c) for c in CHANNELS]
        return np.array([float(values.get(n, 0.0)) for n in names]) if any(n in values for n in names) else None


class PowerGainEffect(PerChannelEffect, GainEffect):
    """A gain error f(u) = 1 + k u^power per channel; ``chain`` stays each
    effect's own, written so that it rounds as the diagnosis always has."""

    power: ClassVar[int]

    def gain(self, k: Any, u: np.ndarray) -> np.ndarray:
        return 1.0 + k * u**self.power

    def gain_derivative(self, u: np.ndarray) -> np.ndarray:
        return u**self.power
