"""Effect sizes to test, drawn across the ranges docs/effects.md gives for the
default test plan (each catalogue effect's ``sizes``; most of them
concealed), and the structures outside the catalogue; used by the
acceptance script, the tests and the demo."""

from __future__ import annotations

import numpy as np

from rotcal.model.effects import effect_named
from rotcal.model.physics import AXES


def draw_effect(name: str, rng: np.random.Generator, part: tuple[float, float] = (0.0, 1.0)) -> str:
    """One effect of ``name`` with a size drawn across the ``part`` of its
    range (fractions from its low end; the whole range by default), in the
    simulator's ``NAME:key=value`` form."""
    effect = effect_named(name)
    low, high = effect.sizes
    size = low + (high - low) * rng.uniform(*part)
    sign = rng.choice([-1.0, 1.0])
    axis = rng.choice(AXES)
    channel = rng.choice(("u", "v", "w"))
    return effect.draw(size, sign, axis, channel, rng)


def draw_foreign(name: str, rng: np.random.Generator) -> str:
    """A structure the catalogue does not hold: a tone of a few counts
    between 1 and 5 Hz in one channel, or an offset step of 10 to 40 counts
    in all channels at a random time."""
    if name == "tone":
        channel = rng.choice(("u", "v", "w"))
        return f"tone:channel={channel},freq_hz={rng.uniform(1.0, 5.0):.6g},amplitude={rng.uniform(2.0, 5.0):.4g}"
    return f"offset_step:size={rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 40.0):.4g}"
