"""The model extensions the diagnosis can add: every effect of effects.md at
its physical granularity (per rotation axis, per channel, or for the whole
dataset) and the generic structures rotcal reports as ``unexplained``.

Internal parameters are chosen so that each extension is smooth at zero
(ripple as (a cos p, a sin p) rather than (a, p)); ``report_parameters``
turns them into the parameters effects.md names, with uncertainties.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotcal.model.physics import AXES, CHANNELS, AxisEffect, Effects

ALL = (0, 1, 2)


@dataclass(frozen=True)
class Candidate:
    """One extension: ``effect`` (an effects.md name, or ``unexplained``) on
    ``scope`` (an axis, a channel, or '' for the whole dataset), with its
    internal parameter names and, per parameter, the channels it enters."""

    effect: str
    scope: str
    names: tuple[str, ...]
    channels: tuple[tuple[int, ...], ...]

    @property
    def key(self) -> str:
        return f"{self.effect}@{self.scope}" if self.scope else self.effect


def across(axis: str) -> tuple[str, str]:
    """The two table axes perpendicular to ``axis``."""
    a, b = (s for s in AXES if s != axis)
    return a, b


def catalogue(rotating_axes: tuple[str, ...], all_axes: tuple[str, ...], angles_measured: bool) -> tuple[Candidate, ...]:
    """Every catalogue extension testable on a dataset with these segments."""
    out: list[Candidate] = []
    for s in rotating_axes:
        a, b = across(s)
        out.append(Candidate("centripetal", s, (f"centripetal.{s}.d_{a}_m", f"centripetal.{s}.d_{b}_m"), (ALL, ALL)))
    for r, c in enumerate(CHANNELS):
        out.append(Candidate("cubic_nonlinearity", c, (f"k3_{c}",), ((r,),)))
        out.append(Candidate("quadratic_nonlinearity", c, (f"k2_{c}",), ((r,),)))
        out.append(Candidate("offset_drift", c, (f"drift_{c}",), ((r,),)))
    if rotating_axes:
        for r, c in enumerate(CHANNELS[1:], start=1):
            out.append(Candidate("channel_delay", c, (f"delay_{c}_s",), ((r,),)))
    if rotating_axes and not angles_measured:
        out.append(Candidate("rate_error", "", ("rate_error",), (ALL,)))
        for s in rotating_axes:
            out.append(Candidate("rate_ripple", s, (f"ripple.{s}.a_deg", f"ripple.{s}.b_deg"), (ALL, ALL)))
    for s in all_axes:
        out.append(Candidate("axis_tilt", s, (f"tilt.{s}_deg",), (ALL,)))
    return tuple(out)


STEP = Candidate("unexplained", "step", tuple(f"step_{c}" for c in CHANNELS), ((0,), (1,), (2,)))


def effects_from(values: dict[str, float], clip: tuple[float | None, float | None]) -> Effects:
    """A physics.Effects from internal parameter values (missing = 0)."""
    get = lambda name: float(values.get(name, 0.0))  # noqa: E731
    centripetal, ripple, tilt = [], [], []
    for s in AXES:
        a, b = across(s)
        if f"centripetal.{s}.d_{a}_m" in values:
            d = np.zeros(3)
            d[AXES.index(a)] = get(f"centripetal.{s}.d_{a}_m")
            d[AXES.index(b)] = get(f"centripetal.{s}.d_{b}_m")
            centripetal.append(AxisEffect(s, tuple(d)))
        if f"ripple.{s}.a_deg" in values:
            alpha, beta = get(f"ripple.{s}.a_deg"), get(f"ripple.{s}.b_deg")
            ripple.append(AxisEffect(s, (float(np.hypot(alpha, beta)), float(np.degrees(np.arctan2(beta, alpha))))))
        if f"tilt.{s}_deg" in values:
            tilt.append(AxisEffect(s, (get(f"tilt.{s}_deg"),)))
    return Effects(
        centripetal=tuple(centripetal),
        k3=tuple(get(f"k3_{c}") for c in CHANNELS),
        k2=tuple(get(f"k2_{c}") for c in CHANNELS),
        clip_low=clip[0],
        clip_high=clip[1],
        delay_s=(0.0, get("delay_v_s"), get("delay_w_s")),
        rate_error=get("rate_error"),
        rate_ripple=tuple(ripple),
        axis_tilt=tuple(tilt),
        drift=tuple(get(f"drift_{c}") for c in CHANNELS),
    )


@dataclass(frozen=True)
class ReportedParameter:
    name: str
    value: float
    std_uncertainty: float
    unit: str


def report_parameters(cand: Candidate, value: np.ndarray, cov: np.ndarray, output_unit: str) -> list[ReportedParameter]:
    """The effects.md parameters of a fitted extension, by first-order propagation."""
    u = np.sqrt(np.diag(cov))
    if cand.effect == "centripetal":
        radius = float(np.hypot(*value))
        grad = value / radius if radius > 0 else np.zeros(2)
        names = [n.split(".")[-1] for n in cand.names]
        return [ReportedParameter("radius_m", radius, float(np.sqrt(grad @ cov @ grad)), "m")] + [
            ReportedParameter(n, float(v), float(s), "m") for n, v, s in zip(names, value, u)
        ]
    if cand.effect == "rate_ripple":
        alpha, beta = value
        amp = float(np.hypot(alpha, beta))
        g_amp = np.array([alpha, beta]) / amp if amp > 0 else np.zeros(2)
        g_phase = np.degrees(np.array([-beta, alpha]) / max(amp**2, 1e-300))
        return [
            ReportedParameter("ripple_deg", amp, float(np.sqrt(g_amp @ cov @ g_amp)), "degree"),
            ReportedParameter("ripple_phase_deg", float(np.degrees(np.arctan2(beta, alpha)) % 360.0),
                              float(np.sqrt(g_phase @ cov @ g_phase)), "degree"),
        ]
    if cand.effect == "axis_tilt":
        # the model holds the tilt through its sine and cosine, so the fit may settle a whole turn away
        return [ReportedParameter("tilt_deg", float((value[0] + 180.0) % 360.0 - 180.0), float(u[0]), "degree")]
    units = {"channel_delay": "s", "offset_drift": f"{output_unit} per s"}
    return [ReportedParameter(n, float(v), float(s), units.get(cand.effect, "1")) for n, v, s in zip(cand.names, value, u)]
