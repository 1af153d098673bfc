"""``thermal``: the DUT's offsets and sensitivities depend on its temperature
T (the logged ``temperature_c``): O_r -> O_r + tco_r (T - T_ref) and
s_r -> s_r (1 + tcs_r (T - T_ref)), T_ref the mean temperature of the
samples the model sees (the whole recording in the simulator, the fitted
segments' samples in the diagnosis: a different T_ref only moves the
baseline offsets and sensitivities, which are fitted).

Both an offset term (stage 5) and a per-sample sensitivity factor (stage
4b, ``ScaleEffect``): one state, (tco, tcs) per channel.

Simulator option ``thermal:KEY=VALUE,...``:

- ``tco_u, tco_v, tco_w``: offset coefficients (output unit per K);
- ``tcs_u, tcs_v, tcs_w``: sensitivity coefficients (1/K);
- ``warmup_k``: the warm-up's size, K (drawn from 3 to 8 K if not given;
  negative for a cool-down);
- ``tau_frac``: the warm-up's time constant as a fraction of the session
  (drawn from 0.1 to 0.4 if not given);
- ``start_c``: the temperature at the first sample, degree C (drawn from
  20 to 25);
- ``step_k``, ``step_frac``: a step of ``step_k`` K (the lab's air
  conditioning cycling) at ``step_frac`` of the session (0 K unless given;
  its time drawn from 0.2 to 0.8 if not given).

The temperature history is T(t) = start_c + warmup_k (1 - exp(-(t - t0) /
(tau_frac D))) + step_k [t >= t0 + step_frac D], D the session's duration;
it is written as the ``temperature_c`` column.

The diagnosis tests it only on datasets whose samples carry a varying
``temperature_c`` (``needs``); its design columns are T - T_ref (the
offset) and (T - T_ref) times the channel's gained output (the sensitivity).
"""

from __future__ import annotations

import numpy as np

from rotcal.errors import ConfigError
from rotcal.model.conventions import CHANNELS, Motion
from rotcal.model.effects.base import Candidate, Channel, ColumnContext, OffsetEffect, Parameter, ScaleEffect

COEFFICIENTS = tuple(f"tco_{c}" for c in CHANNELS) + tuple(f"tcs_{c}" for c in CHANNELS)
HISTORY = ("warmup_k", "tau_frac", "start_c", "step_k", "step_frac")


def excursion(motion: Motion) -> np.ndarray:
    """T - T_ref per sample, T_ref the samples' mean temperature."""
    if motion.temperature_c is None:
        raise ConfigError("effect thermal needs each sample's temperature (a temperature_c column)")
    temperature = np.asarray(motion.temperature_c, float)
    return temperature - temperature.mean()


class Thermal(ScaleEffect, OffsetEffect):
    name = "thermal"
    physics = ("offsets and sensitivities depend on the DUT temperature T: O_r -> O_r + tco_r (T - T_ref), "
               "s_r -> s_r (1 + tcs_r (T - T_ref)), T_ref the mean temperature")
    parameters = (tuple(Parameter(f"tco_{c}", "output unit per K", f"offset temperature coefficient of {c}")
                        for c in CHANNELS)
                  + tuple(Parameter(f"tcs_{c}", "1/K", f"sensitivity temperature coefficient of {c}")
                          for c in CHANNELS))
    options = frozenset(COEFFICIENTS + HISTORY)
    sizes_given = frozenset(COEFFICIENTS)
    magnitudes = frozenset({"tau_frac", "step_frac"})
    sizes = (0.3, 2.0)
    size_of = "abs(tco) on one channel, bit per K (with abs(tcs) 20 to 100 ppm per K, a warm-up of 3 to 8 K)"
    where = "channel {s}, against temperature_c"
    needs = frozenset({"temperature_c"})
    listed = 9
    at_rest = "temperature"
    at_rest_steps = {"tco": 1e-2, "tcs": 1e-6}

    # --- the simulator -------------------------------------------------
    def complete(self, params, rng):
        p = super().complete(params, rng)
        p.setdefault("warmup_k", float(rng.uniform(3.0, 8.0)))
        p.setdefault("tau_frac", float(rng.uniform(0.1, 0.4)))
        p.setdefault("start_c", float(rng.uniform(20.0, 25.0)))
        p.setdefault("step_k", 0.0)
        if p["step_k"] != 0.0:
            p.setdefault("step_frac", float(rng.uniform(0.2, 0.8)))
        if p["tau_frac"] <= 0:
            raise ConfigError(f"effect thermal: tau_frac = {p['tau_frac']} must be > 0")
        return p

    def state(self, previous, params):
        k = np.zeros((2, 3)) if previous is None else np.array(previous, float)
        for r, c in enumerate(CHANNELS):
            k[0, r] = params.get(f"tco_{c}", k[0, r])
            k[1, r] = params.get(f"tcs_{c}", k[1, r])
        return k

    def temperature_history(self, params, motion):
        t = motion.t_s - motion.t0_s
        duration = max(float(t.max()), 1e-9)
        temperature = params["start_c"] + params["warmup_k"] * -np.expm1(-t / (params["tau_frac"] * duration))
        if params.get("step_k", 0.0):
            temperature = temperature + params["step_k"] * (t >= params["step_frac"] * duration)
        return temperature

    def offset(self, state, motion):
        return np.asarray(state)[0][None, :] * excursion(motion)[:, None]

    def scale(self, state, motion):
        return 1.0 + np.asarray(state)[1][None, :] * excursion(motion)[:, None]

    def draw(self, size, sign, axis, channel, rng) -> str:
        tcs = rng.uniform(20e-6, 100e-6) * rng.choice([-1.0, 1.0])
        return (f"thermal:tco_{channel}={sign * size:.6g},tcs_{channel}={tcs:.6g},"
                f"warmup_k={rng.uniform(3.0, 8.0):.4g},tau_frac={rng.uniform(0.1, 0.4):.4g}")

    # --- the diagnosis -------------------------------------------------
    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, c, (f"tco_{c}", f"tcs_{c}"), ((r,), (r,))) for r, c in enumerate(CHANNELS))

    def state_from(self, values):
        if not any(n in values for n in COEFFICIENTS):
            return None
        return np.array([[float(values.get(f"{kind}_{c}", 0.0)) for c in CHANNELS] for kind in ("tco", "tcs")])

    def column(self, name: str, cand: Candidate, st: Channel, ctx: ColumnContext,
               out: np.ndarray | None = None) -> np.ndarray:
        dT = ctx.cached("thermal", lambda: excursion(ctx.motion))
        if name.startswith("tco_"):
            return dT
        return ctx.scale_column(self, st, dT, out)


EFFECT = Thermal()
