"""``clipping``: the output saturates, R -> min(max(R, clip_low), clip_high),
with the same limits on every channel (a converter property), after noise
and rounding. The diagnosis finds the limits from runs of samples stuck at
the extremes (``rotcal.diagnose.clipping``) and reports only the limits the
data reach, with an uncertainty of at least one output unit."""

from __future__ import annotations

import numpy as np

from rotcal.model.effects.base import LimitEffect, Parameter


class Clipping(LimitEffect):
    name = "clipping"
    physics = "the output saturates: R -> min(max(R, clip_low), clip_high)"
    parameters = (Parameter("clip_low", "output unit", "lower limit"), Parameter("clip_high", "output unit", "upper limit"))
    # below_max / above_min: a limit as a fraction below the largest (above the smallest) noise-free output
    options = frozenset({"clip_low", "clip_high", "below_max", "above_min"})
    magnitudes = frozenset({"below_max", "above_min"})
    sizes = (0.002, 0.008)
    size_of = "the limit, as a fraction below the largest output"
    where = "every channel's extremes"
    listed = 3
    not_at_rest = "not tested on static poses"

    def state(self, previous, params):
        return params.get("clip_low"), params.get("clip_high")

    def resolve(self, params, clean) -> bool:
        """Limits given as fractions become numbers, from the noise-free output."""
        high, low = params.get("clip_high"), params.get("clip_low")
        if "below_max" in params:
            peak = float(clean.max())
            high = float(np.floor(peak - params.pop("below_max") * abs(peak)))
        if "above_min" in params:
            trough = float(clean.min())
            low = float(np.ceil(trough + params.pop("above_min") * abs(trough)))
        params.update({k: v for k, v in (("clip_high", high), ("clip_low", low)) if v is not None})
        return True

    def limits(self, state):
        return state

    def draw(self, size, sign, axis, channel, rng) -> str:
        return f"clipping:below_max={size:.6g}"

    def state_from(self, values):
        low, high = values.get("clip_low"), values.get("clip_high")
        return None if low is None and high is None else (low, high)


EFFECT = Clipping()
