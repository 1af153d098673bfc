"""Effect sizes to test, drawn across the ranges effects.md gives for the
default test plan (most of them concealed), and the structures outside the
catalogue; used by the acceptance script, the tests and the demo."""

from __future__ import annotations

import numpy as np

from rotcal.model.physics import AXES

RANGES = {
    "centripetal": (0.03, 0.25),
    "cubic_nonlinearity": (3e-4, 1.2e-3),
    "quadratic_nonlinearity": (2e-4, 8e-4),
    "clipping": (0.002, 0.008),
    "channel_delay": (0.5e-3, 6e-3),
    "rate_error": (5e-5, 4e-4),
    "rate_ripple": (0.03, 0.2),
    "axis_tilt": (0.08, 0.5),
    "offset_drift": (0.006, 0.03),
}


def draw_effect(name: str, rng: np.random.Generator) -> str:
    """One effect of ``name`` with a size drawn across its range, in the
    simulator's ``NAME:key=value`` form."""
    low, high = RANGES[name]
    size = rng.uniform(low, high)
    sign = rng.choice([-1.0, 1.0])
    axis = rng.choice(AXES)
    channel = rng.choice(("u", "v", "w"))
    if name == "centripetal":
        return f"centripetal:axis={axis},radius_m={size:.6g}"
    if name == "cubic_nonlinearity":
        return f"cubic_nonlinearity:k3_{channel}={sign * size:.6g}"
    if name == "quadratic_nonlinearity":
        return f"quadratic_nonlinearity:k2_{channel}={sign * size:.6g}"
    if name == "clipping":
        return f"clipping:below_max={size:.6g}"
    if name == "channel_delay":
        which = rng.choice(("v", "w", "vw"))
        parts = [f"delay_{c}_s={rng.uniform(low, high):.6g}" for c in which]
        return "channel_delay:" + ",".join(parts)
    if name == "rate_error":
        return f"rate_error:rate_error={sign * size:.6g}"
    if name == "rate_ripple":
        return f"rate_ripple:axis={axis},ripple_deg={size:.6g}"
    if name == "axis_tilt":
        return f"axis_tilt:axis={axis},tilt_deg={sign * size:.6g}"
    return f"offset_drift:drift_{channel}={sign * size:.6g}"


def draw_foreign(name: str, rng: np.random.Generator) -> str:
    """A structure the catalogue does not hold: a tone of a few counts
    between 1 and 5 Hz in one channel, or an offset step of 10 to 40 counts
    in all channels at a random time."""
    if name == "tone":
        channel = rng.choice(("u", "v", "w"))
        return f"tone:channel={channel},freq_hz={rng.uniform(1.0, 5.0):.6g},amplitude={rng.uniform(2.0, 5.0):.4g}"
    return f"offset_step:size={rng.choice([-1.0, 1.0]) * rng.uniform(10.0, 40.0):.4g}"
