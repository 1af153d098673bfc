"""The effect catalogue: the physics of docs/effects.md that the papers' linear
model leaves out, one module per effect. The simulator (``rotcal.simulate``), the forward model
(``rotcal.model.physics``) and the diagnosis (``rotcal.diagnose``) all read
this registry; a new effect is a new module here that defines ``EFFECT``
(``base`` says what an effect is, ``families`` holds implementations
several effects share). Each effect carries every fact the stages need of
it: its forward-model stage, parameters, simulator option, diagnosis
model, what a DUT at rest shows of it (``at_rest``) and whether a
rotation's own-phase fit absorbs it (``absorbed_by_own_phase``).

``catalogue()`` lists the effects in the forward model's order (by stage,
then by their row in docs/effects.md's table), ``listed()`` in the table's order
(the order of the diagnosis table).
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from rotcal.errors import ConfigError
from rotcal.model.effects.base import (
    AngleEffect,
    Effect,
    ForceEffect,
    GainEffect,
    LimitEffect,
    OffsetEffect,
    SamplingEffect,
    ScaleEffect,
    stage_rank,
)

E = TypeVar("E", bound=Effect)


def _discover() -> list[Effect]:
    """The ``EFFECT`` of every module of this package that defines one
    (``base`` and ``families`` define none, ``__main__`` is not imported)."""
    modules = (importlib.import_module(f"{__name__}.{m.name}") for m in pkgutil.iter_modules(__path__)
               if not m.name.startswith("_"))
    return [m.EFFECT for m in modules if hasattr(m, "EFFECT")]


_REGISTRY: list[Effect] = []


def register(effect: Effect) -> None:
    """Add an effect to the catalogue (the modules here are added on import)."""
    if any(e.name == effect.name for e in _REGISTRY):
        raise ValueError(f"effect {effect.name!r} is already in the catalogue")
    _REGISTRY.append(effect)
    _REGISTRY.sort(key=lambda e: (stage_rank(e), e.listed, e.name))


@contextmanager
def registered(effect: Effect) -> Iterator[Effect]:
    """The catalogue with ``effect`` added for the duration (tests)."""
    register(effect)
    try:
        yield effect
    finally:
        _REGISTRY.remove(effect)


for _effect in _discover():
    register(_effect)


def catalogue() -> tuple[Effect, ...]:
    """The effects in the forward model's order."""
    return tuple(_REGISTRY)


def listed() -> tuple[Effect, ...]:
    """The effects in the order of docs/effects.md's table."""
    return tuple(sorted(_REGISTRY, key=lambda e: (e.listed, e.name)))


def names() -> tuple[str, ...]:
    return tuple(e.name for e in listed())


def effect_named(name: str) -> Effect:
    for e in _REGISTRY:
        if e.name == name:
            return e
    raise ConfigError(f"unknown effect {name!r}; known: {', '.join(names())}")


def table() -> str:
    """The catalogue as a Markdown table (``python -m rotcal.model.effects``):
    each effect's physics, parameters with units, and the sizes to test on
    the default plan."""
    rows = ["| effect | physics and model | parameters (unit) | sizes to test |", "|---|---|---|---|"]
    for e in listed():
        params = "; ".join(f"`{p.name}` ({p.unit}): {p.meaning}" for p in e.parameters)
        rows.append(f"| `{e.name}` | {e.physics} | {params} | {e.size_of}: {e.sizes[0]:g} to {e.sizes[1]:g} |")
    return "\n".join(rows) + "\n"


@dataclass(frozen=True, eq=False)
class Effects:
    """The effects switched on, by name, with their states; none is the
    papers' linear model."""

    states: Mapping[str, Any] = field(default_factory=dict)

    def active(self, stage: type[E]) -> list[tuple[E, Any]]:
        """(effect, state) of the switched-on effects of one stage, in order."""
        return [(e, self.states[e.name]) for e in _REGISTRY if isinstance(e, stage) and e.name in self.states]

    def with_state(self, name: str, state: Any) -> Effects:
        return Effects({**self.states, name: state})

    def rate_factor(self) -> float:
        """The true rotation rate over the commanded one."""
        factor = 1.0
        for effect, state in self.active(AngleEffect):
            factor = factor * effect.rate_factor(state)
        return factor

    def delays(self) -> tuple[float, float, float]:
        """Each channel's sampling instant after its stamp (s)."""
        total = np.zeros(3)
        for effect, state in self.active(SamplingEffect):
            total = total + np.asarray(effect.delays(state), float)
        return (float(total[0]), float(total[1]), float(total[2]))

    def limits(self) -> tuple[float, float]:
        """The output's (low, high) limits, infinite where none."""
        low, high = -np.inf, np.inf
        for effect, state in self.active(LimitEffect):
            lo, hi = effect.limits(state)
            low = low if lo is None else max(low, lo)
            high = high if hi is None else min(high, hi)
        return low, high


__all__ = ["AngleEffect", "Effect", "Effects", "ForceEffect", "GainEffect", "LimitEffect", "OffsetEffect",
           "SamplingEffect", "ScaleEffect", "catalogue", "effect_named", "listed", "names", "register", "registered", "table"]
