"""Simulate: synthetic datasets from the forward model (``rotcal.model.physics``)
with the test plan of Gaitan & Geist 2021 (the defaults of
``rotcal.simulate.spec.Plan``), any effect of the catalogue (``rotcal.model.effects``)
switched on, seeded and deterministic. The truth used is returned with the
samples and written beside the data (``rotcal.simulate.writers``); the
request is a ``SimulationSpec`` (``rotcal.simulate.spec``)."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import asdict, replace

import numpy as np
import polars as pl

from rotcal import __version__
from rotcal.errors import ConfigError
from rotcal.model.effects import effect_named
from rotcal.model.physics import (
    CHANNELS,
    INTRINSIC,
    Dut,
    Effects,
    Motion,
    axis_index,
    intrinsic_from_vectors,
    noise_free_output,
    nonlinearity,
    observe,
    offset_terms,
    rotation_matrix,
    scale_terms,
    scaled,
    unit_vectors_from_angles,
)
from rotcal.simulate.noise import NoiseSpec, draw_channels, noise_terms, quantized
from rotcal.simulate.noise_request import resolve_noise
from rotcal.simulate.spec import DutSpec, Plan, Simulation, SimulationSpec
from rotcal.simulate.timebase_sim import apply_defects
from rotcal.simulate.transitions import schedule_continuous, timeline
from rotcal.simulate.writers import table_messages


def draw_dut(spec: DutSpec, rng: np.random.Generator) -> tuple[Dut, dict]:
    """A DUT with random intrinsic parameters and a random mount rotation."""
    s = spec.sensitivity + rng.uniform(-spec.sensitivity_spread, spec.sensitivity_spread, 3)
    phi = 90.0 + rng.uniform(-spec.angle_spread_deg, spec.angle_spread_deg, 3)
    offsets = rng.uniform(-spec.offset_range, spec.offset_range, 3)
    mount_axis = rng.standard_normal(3)
    mount_deg = rng.uniform(0.0, spec.misalignment_max_deg)
    unit = unit_vectors_from_angles(*phi) @ rotation_matrix(mount_axis, mount_deg).T
    dut = Dut(unit * s[:, None], offsets, np.full(3, spec.noise_std), spec.full_scale or None, spec.integer_output)
    mount = {"mount_axis": (mount_axis / np.linalg.norm(mount_axis)).tolist(), "mount_angle_deg": mount_deg}
    return dut, mount


def build_effects(requests: tuple, rng: np.random.Generator) -> tuple[Effects, list[dict]]:
    """The catalogue's effects from requests (name, parameters), each
    completed by its effect (random where the request leaves a choice), in
    the request order; limits given relative to the output are resolved
    later (``_resolve``)."""
    states: dict = {}
    described = []
    for name, params in requests:
        effect = effect_named(name)
        p = effect.complete(dict(params), rng)
        described.append({"effect": name, "axis": p.get("axis", ""), "parameters": {k: v for k, v in p.items() if k != "axis"}})
        states[name] = effect.state(states.get(name), p)
    return Effects(states), described


def plan_parts(plan: Plan, rng: np.random.Generator) -> Iterator[dict]:
    """The plan's segments in order, one at a time: sample times (int64 ns),
    axis, rate, commanded angles and segment number.

    Per axis: the static steps (logging paused ``step_move_s`` while the table
    moves), then each rate; logging paused ``pause_s`` between segments. A
    rotation's start angle is drawn from ``rng`` when its segment is reached.
    """
    dt_ns = int(round(plan.dt_s * 1e9))
    t_next, seg = 0, 0
    for axis in plan.axes:
        steps = np.arange(0.0, 360.0, plan.step_deg)
        step_start = t_next + np.arange(steps.size) * (plan.step_samples * dt_ns + int(plan.step_move_s * 1e9))
        t = (step_start[:, None] + np.arange(plan.step_samples)[None, :] * dt_ns).ravel()
        yield dict(t_ns=t, axis=axis, rate_hz=0.0, angle=np.repeat(steps, plan.step_samples), seg=seg)
        t_next, seg = int(t[-1]) + int(plan.pause_s * 1e9), seg + 1
        for rate in plan.rates_hz:
            t = t_next + np.arange(plan.rotation_samples, dtype=np.int64) * dt_ns
            theta0 = rng.uniform(0.0, 360.0)
            angle = theta0 + 360.0 * rate * (t - t[0]) / 1e9
            yield dict(t_ns=t, axis=axis, rate_hz=rate, angle=angle, seg=seg)
            t_next, seg = int(t[-1]) + int(plan.pause_s * 1e9), seg + 1


def schedule(plan: Plan, rng: np.random.Generator) -> tuple[Motion, pl.DataFrame]:
    """Sample times and commanded motion of the plan (``plan_parts``), with per-sample labels."""
    parts = list(plan_parts(plan, rng))
    sizes = [p["t_ns"].size for p in parts]
    t_ns = np.concatenate([p["t_ns"] for p in parts]).astype(np.int64)
    rate = np.repeat([p["rate_hz"] for p in parts], sizes)
    t_start = np.repeat([p["t_ns"][0] / 1e9 for p in parts], sizes)
    motion = Motion(
        t_s=t_ns / 1e9,
        axis_idx=np.repeat([axis_index(p["axis"]) for p in parts], sizes),
        rotating=rate != 0,
        theta_cmd_deg=np.concatenate([p["angle"] for p in parts]),
        t_start_s=t_start,
        rate_hz=rate,
        t0_s=t_ns[0] / 1e9,
    )
    labels = pl.DataFrame({
        "t_ns": t_ns,
        "axis": np.repeat([p["axis"] for p in parts], sizes),
        "rate_hz": rate,
        "angle_deg": motion.theta_cmd_deg,
        "plan_segment": np.repeat([p["seg"] for p in parts], sizes).astype(np.int32),
    })
    return motion, labels


def simulate(spec: SimulationSpec, seed: int) -> Simulation:
    """One dataset. Independent random streams for the DUT, the plan, the
    effects, the noise and the logger keep a seed's DUT and noise the same
    whatever effects are switched on."""
    streams = np.random.SeedSequence(seed).spawn(5)
    dut_rng, plan_rng, effect_rng, noise_rng, logger_rng = (np.random.default_rng(s) for s in streams)
    dut, mount = draw_dut(spec.dut, dut_rng)
    effects, described = build_effects(spec.effects, effect_rng)
    phases = None
    if spec.plan.continuous:
        motion, labels, phases, hand = schedule_continuous(spec.plan, effects.rate_factor(), plan_rng)
    else:
        motion, labels = schedule(spec.plan, plan_rng)
    motion = _with_temperature(motion, described)
    clean = noise_free_output(motion, dut, effects, spec.g_local)
    if phases is not None and hand.mask.any():
        # a hand move: the same output chain after r . a (docs/effects.md order) with the hand's specific force
        linear = hand.specific_force(spec.g_local) @ dut.responsivity.T
        x1g = np.linalg.norm(dut.responsivity, axis=1) * spec.g_local
        scale = scale_terms(motion, effects)
        gained = scaled(nonlinearity(linear, x1g, effects), None if scale is None else scale[hand.mask])
        clean[hand.mask] = dut.offsets + offset_terms(motion, effects)[hand.mask] + gained
    effects = _resolve(effects, described, clean)
    clean, foreign = _add_foreign(clean, motion, spec.foreign, effect_rng)
    noise = dut_noise(spec)
    if noise is None:
        observed = observe(clean, dut, effects, noise_rng)
    else:
        dut = replace(dut, noise_std=np.full(3, noise.white_sd))
        drawn = noise_at(noise, motion.t_s, 1 / spec.plan.dt_s, noise_rng)
        observed = observe(quantized(clean + drawn, noise.quantization), replace(dut, noise_std=np.zeros(3)), effects, noise_rng)
    logged = () if motion.temperature_c is None else (pl.Series("temperature_c", motion.temperature_c),)
    samples = labels.with_columns(
        *(pl.Series(c, observed[:, r]) for r, c in enumerate(CHANNELS)), *logged
    ).select("t_ns", *CHANNELS, "axis", "rate_hz", "angle_deg", "plan_segment", *(s.name for s in logged))
    table = table_messages(samples.filter(pl.col("plan_segment").is_not_null()))
    table = table.with_columns(t_ns=pl.Series(np.round(table["t_ns"].to_numpy() * spec.timebase.clock_factor).astype(np.int64)))
    samples, logger = apply_defects(samples, spec.timebase, logger_rng)
    truth = truth_record(spec, seed, dut, mount, described, foreign, logger)
    if noise is not None:
        fs_hz = 1 / spec.plan.dt_s
        truth["noise"] = {"preset": spec.noise[0], "sample_rate_hz": fs_hz, "spec": asdict(noise),
                          "terms": noise_terms(noise, fs_hz)}
    if phases is not None:
        truth["timeline"] = timeline(phases, spec.timebase.clock_factor)
    return Simulation(samples, truth, dut, effects, table)


def dut_noise(spec: SimulationSpec) -> NoiseSpec | None:
    """The DUT's noise in counts (the request's preset resolved for the
    DUT's nominal sensitivity and the plan's sample rate), None for the
    white noise of ``dut.noise_std``."""
    name, values = spec.noise
    if not name and not values:
        return None
    return resolve_noise(name, values, spec.dut.sensitivity, 1 / spec.plan.dt_s)


def noise_at(noise: NoiseSpec, t_s: np.ndarray, fs_hz: float, rng: np.random.Generator) -> np.ndarray:
    """The noise (n, 3) at sample times ``t_s``: drawn on the sensor's own
    sample grid from the first sample to the last (the sensor's filters and
    wander run on while the logger pauses) and taken at the samples."""
    k = np.round((t_s - t_s[0]) * fs_hz).astype(np.int64)
    return draw_channels(noise, int(k.max()) + 1 if k.size else 0, fs_hz, rng, 3)[k]


def truth_record(spec: SimulationSpec, seed: int, dut: Dut, mount: dict, described: list[dict], foreign: list,
                 logger: dict) -> dict:
    """What was simulated (``truth.json``): the DUT, plan, effects and logger defects."""
    return {
        "rotcal_version": __version__,
        "seed": seed,
        "g_local": spec.g_local,
        "g_local_uncertainty": spec.g_local_uncertainty,
        "output_unit": spec.output_unit,
        "intrinsic": dict(zip(INTRINSIC, intrinsic_from_vectors(dut.responsivity, dut.offsets).tolist())),
        "dut": {"responsivity": dut.responsivity.tolist(), "offsets": dut.offsets.tolist(),
                "noise_std": dut.noise_std.tolist(), "full_scale": dut.full_scale, **mount},
        "plan": asdict(spec.plan),
        "effects": described,
        "foreign": foreign,
        "timebase": logger,
    }


def _with_temperature(motion: Motion, described: list[dict]) -> Motion:
    """The motion with the DUT temperature of each sample, when a requested
    effect draws a temperature history (the last such request's)."""
    for d in described:
        history = effect_named(d["effect"]).temperature_history(d["parameters"], motion)
        if history is not None:
            motion = replace(motion, temperature_c=history)
    return motion


def _add_foreign(clean: np.ndarray, motion: Motion, requests: tuple, rng: np.random.Generator) -> tuple[np.ndarray, list]:
    """Add structures no catalogue effect describes: a tone in one channel
    (coherent over the recording) or an offset step in all channels."""
    out, described = clean.copy(), []
    t = motion.t_s
    for name, params in requests:
        p = dict(params)
        if name == "tone":
            channel = p.get("channel", "w")
            if channel not in CHANNELS:
                raise ConfigError("foreign tone needs channel=u, v or w")
            p.setdefault("phase_deg", rng.uniform(0, 360))
            unknown = sorted(set(p) - {"channel", "freq_hz", "amplitude", "phase_deg"})
            if unknown or "freq_hz" not in p or "amplitude" not in p:
                raise ConfigError("foreign tone takes channel, freq_hz, amplitude and phase_deg")
            out[:, CHANNELS.index(channel)] += p["amplitude"] * np.sin(2 * np.pi * p["freq_hz"] * t + np.deg2rad(p["phase_deg"]))
        else:
            p.setdefault("t_s", float(rng.uniform(t[0], t[-1])))
            if sorted(set(p) - {"t_s", "size"}) or "size" not in p:
                raise ConfigError("foreign offset_step takes t_s and size")
            out[t >= p["t_s"]] += p["size"]
        described.append({"structure": name, "parameters": p})
    return out, described


def _resolve(effects: Effects, described: list[dict], clean: np.ndarray) -> Effects:
    """Parameters that depend on the noise-free output (e.g. a clip limit
    asked for as a fraction below the largest output) become numbers."""
    for d in described:
        effect = effect_named(d["effect"])
        if effect.resolve(d["parameters"], clean):
            effects = effects.with_state(effect.name, effect.state(None, {"axis": d["axis"], **d["parameters"]}))
    return effects

