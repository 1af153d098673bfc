"""The forward model: the conventions of docs/conventions.md
(``rotcal.model.conventions``) with the effects of the catalogue
(``rotcal.model.effects``), applied in the order docs/effects.md gives, for each
sample and channel:

1. the commanded angle becomes the true angle (angle effects; rotation
   segments only, static steps are exact), evaluated at the channel's true
   sampling instant (sampling effects);
2. gravity (Geist 2017 Eq. 5) changed by gravity effects, plus added
   force terms, gives the specific force a;
3. y = r . a, then the gain effects act on y, then the scale effects
   multiply it;
4. the offset plus offset effects;
5. white noise, rounding to the integer output, then output limits.

The simulator and the diagnosis both evaluate this one model, so what
rotcal simulates is exactly what it fits.
"""

from __future__ import annotations

import numpy as np

from rotcal.model.constants import STANDARD_GRAVITY, STANDARD_GRAVITY_UNCERTAINTY
from rotcal.model.conventions import (
    ANGLE_PAIRS,
    AXES,
    CHANNELS,
    COS_COMPONENT,
    INTRINSIC,
    JOINT_SIGN,
    SIN_COMPONENT,
    Dut,
    Motion,
    axis_index,
    gravity_direction,
    gravity_direction_derivative,
    intrinsic_from_vectors,
    rotation_matrix,
    unit_vectors_from_angles,
)
from rotcal.model.effects import AngleEffect, Effects, ForceEffect, GainEffect, OffsetEffect, ScaleEffect

__all__ = [
    "ANGLE_PAIRS", "AXES", "CHANNELS", "COS_COMPONENT", "INTRINSIC", "JOINT_SIGN", "SIN_COMPONENT", "STANDARD_GRAVITY",
    "STANDARD_GRAVITY_UNCERTAINTY", "Dut", "Effects", "Motion", "axis_index", "channel_forces", "gravity_direction",
    "gravity_direction_derivative", "intrinsic_from_vectors", "noise_free_output", "nonlinearity", "observe",
    "offset_terms", "rotation_matrix", "scale_terms", "scaled", "specific_force", "true_angle", "uniform_angle", "unit_vectors_from_angles",
]


def uniform_angle(motion: Motion, effects: Effects, delay_s: float) -> np.ndarray:
    """The rotating samples' angle at the true rate, before angle terms:
    theta0 + 360 rate (1 + e) (t + delay - t_start), written as each
    sample's commanded angle theta_cmd = theta0 + 360 rate (t - t_start)
    moved by 360 rate (e (t - t_start) + (1 + e) delay). The stamps then
    enter only through the effects' small terms, as the segment fits see
    them (they fit on the commanded angles): a time base repaired from
    jittery stamps, whose scale is known to a fraction of a ppm, would
    otherwise put a chirp of a few output units into every long rotation
    and be read as an effect."""
    rot = motion.rotating
    factor = effects.rate_factor()
    moved = (factor - 1.0) * (motion.t_s[rot] - motion.t_start_s[rot]) + factor * delay_s
    return motion.theta_cmd_deg[rot] + 360.0 * motion.rate_hz[rot] * moved


def true_angle(motion: Motion, effects: Effects, delay_s: float) -> np.ndarray:
    """The true table angle seen by a channel sampled ``delay_s`` after its
    stamp: the uniform angle at the true rate plus each angle effect's term
    (e.g. ``rate_ripple``); static steps are exact (docs/effects.md, order)."""
    theta = motion.theta_cmd_deg.astype(float).copy()
    base = uniform_angle(motion, effects, delay_s)
    true = base
    for effect, state in effects.active(AngleEffect):
        term = effect.angle(state, motion, base)
        if term is not None:
            true = true + term
    theta[motion.rotating] = true
    return theta


def specific_force(motion: Motion, effects: Effects, g_local: float, delay_s: float,
                   up: np.ndarray | None = None) -> np.ndarray:
    """Specific force (m/s^2, table frame) for a channel sampled ``delay_s``
    late: gravity of Geist Eq. 5 changed by the gravity effects (e.g.
    ``axis_tilt``), then the added force terms (e.g. ``centripetal``).
    ``up``: gravity's direction at the true angles (``gravity_direction``),
    where the caller has it."""
    if up is None:
        up = gravity_direction(motion.axis_idx, true_angle(motion, effects, delay_s))
    a = g_local * up
    factor = effects.rate_factor()
    for effect, state in effects.active(ForceEffect):
        effect.force(state, motion, a, g_local, factor)
    return a


def channel_forces(motion: Motion, effects: Effects, g_local: float) -> list[np.ndarray]:
    """The specific force each channel sees (its own sampling instant)."""
    delays = effects.delays()
    if not any(delays):
        return [specific_force(motion, effects, g_local, 0.0)] * 3
    return [specific_force(motion, effects, g_local, delays[r]) for r in range(3)]


def nonlinearity(y: np.ndarray, x1g: np.ndarray, effects: Effects) -> np.ndarray:
    """The gain effects acting on the offset-free output y (n, 3): y times
    each one's factor f(y / x1g)."""
    ratio = y / x1g
    out = y
    for effect, k in effects.active(GainEffect):
        out = out * effect.gain(np.asarray(k), ratio)
    return out


def scale_terms(motion: Motion, effects: Effects) -> np.ndarray | None:
    """The scale effects' factors (n, 3), multiplied together; None when
    there are none (the output is then left exactly as it was)."""
    out = None
    for effect, state in effects.active(ScaleEffect):
        factor = effect.scale(state, motion)
        out = factor if out is None else out * factor
    return out


def scaled(gained: np.ndarray, scale: np.ndarray | None) -> np.ndarray:
    """The gained output times the scale effects' factor (unchanged without one)."""
    return gained if scale is None else gained * scale


def offset_terms(motion: Motion, effects: Effects) -> np.ndarray:
    """The offset effects' terms (n, 3), added to the offsets."""
    out = np.zeros((motion.t_s.size, 3))
    for effect, state in effects.active(OffsetEffect):
        out = out + effect.offset(state, motion)
    return out


def noise_free_output(motion: Motion, dut: Dut, effects: Effects, g_local: float) -> np.ndarray:
    """Outputs (n, 3) before noise, rounding and limits (docs/effects.md order)."""
    forces = channel_forces(motion, effects, g_local)
    y = np.column_stack([forces[r] @ dut.responsivity[r] for r in range(3)])
    x1g = np.linalg.norm(dut.responsivity, axis=1) * g_local
    gained = scaled(nonlinearity(y, x1g, effects), scale_terms(motion, effects))
    return dut.offsets[None, :] + offset_terms(motion, effects) + gained


def observe(clean: np.ndarray, dut: Dut, effects: Effects, rng: np.random.Generator) -> np.ndarray:
    """Add white noise, round to the integer output and apply the output
    limits: the limit effects' and the DUT's full scale (docs/effects.md order)."""
    out = clean + rng.standard_normal(clean.shape) * np.asarray(dut.noise_std)[None, :]
    if dut.integer_output:
        out = np.round(out)
    low, high = effects.limits()
    if dut.full_scale is not None:
        low, high = max(low, -dut.full_scale - 1.0), min(high, dut.full_scale)
    return np.clip(out, low, high)
