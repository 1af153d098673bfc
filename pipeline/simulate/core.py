"""Simulate: synthetic datasets from the forward model of ``physics`` with the
test plan of Gaitan & Geist 2021 (contract section 2, "The default test
plan"), any effect of ``effects.md`` switched on, seeded and deterministic.
The truth used is returned with the samples and written beside the data."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import polars as pl

from rotcal import __version__
from rotcal.errors import ConfigError
from rotcal.model.physics import (
    AXES,
    CHANNELS,
    INTRINSIC,
    AxisEffect,
    Dut,
    Effects,
    Motion,
    axis_index,
    drift_term,
    intrinsic_from_vectors,
    noise_free_output,
    nonlinearity,
    observe,
    rotation_matrix,
    unit_vectors_from_angles,
)
from rotcal.simulate.timebase_sim import TimebaseDefects, apply_defects
from rotcal.simulate.transitions import schedule_continuous, timeline

# Structures outside the catalogue of effects.md, for testing that rotcal
# reports them as unexplained instead of forcing them onto a catalogue name.
FOREIGN_NAMES = ("tone", "offset_step")

EFFECT_NAMES = (
    "centripetal", "cubic_nonlinearity", "quadratic_nonlinearity", "clipping", "channel_delay",
    "rate_error", "rate_ripple", "axis_tilt", "offset_drift",
)


@dataclass(frozen=True)
class Plan:
    """The test plan: per axis, a static step sequence then constant rotations.

    ``continuous``: one recording with the transitions recorded too
    (``rotcal.simulate.transitions``): step moves of ``step_move_s``, ramps at
    ``ramp_deg_s2``, a rest of ``pause_s`` after the last rate of an axis and
    a hand reorientation of ``reorient_s`` between axes.
    """

    axes: tuple[str, ...] = AXES
    step_deg: float = 15.0
    step_samples: int = 50
    rates_hz: tuple[float, ...] = (0.01, 0.05, 0.1, 0.5)
    rotation_samples: int = 4200
    dt_s: float = 0.06
    pause_s: float = 5.0
    step_move_s: float = 1.0
    continuous: bool = False
    ramp_deg_s2: float = 10.0
    reorient_s: float = 8.0

    def checked(self) -> Plan:
        """The plan, or a ConfigError naming the first value no plan can have."""
        if not self.axes or any(a not in AXES for a in self.axes):
            raise ConfigError(f"plan: axes = {list(self.axes)!r} must be a non-empty list of x, y, z")
        _require(self, "plan", positive=("step_deg", "dt_s", "ramp_deg_s2"),
                 not_negative=("pause_s", "step_move_s", "reorient_s"), counts=("step_samples", "rotation_samples"))
        if not all(_is_number(f) for f in self.rates_hz):
            raise ConfigError(f"plan: rates_hz = {self.rates_hz!r} must be a list of numbers")
        return self


@dataclass(frozen=True)
class DutSpec:
    """How a DUT is drawn: nominal values and the spread of each."""

    sensitivity: float = 1669.0
    sensitivity_spread: float = 4.0
    angle_spread_deg: float = 0.15
    offset_range: float = 600.0
    misalignment_max_deg: float = 4.0
    noise_std: float = 8.0
    full_scale: float = 32767.0   # 0: no limit (an output in g or m/s^2 need not have one)
    integer_output: bool = True

    def checked(self) -> DutSpec:
        """The DUT spec, or a ConfigError naming the first value no DUT can have."""
        _require(self, "dut", not_negative=("sensitivity_spread", "angle_spread_deg", "offset_range",
                                            "misalignment_max_deg", "noise_std", "full_scale"))
        if not _is_number(self.sensitivity) or self.sensitivity == 0:
            raise ConfigError(f"dut: sensitivity = {self.sensitivity!r} must be a non-zero number")
        if not isinstance(self.integer_output, bool):
            raise ConfigError(f"dut: integer_output = {self.integer_output!r} must be true or false")
        return self


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)


def _require(spec, table: str, positive: tuple[str, ...] = (), not_negative: tuple[str, ...] = (),
             counts: tuple[str, ...] = ()) -> None:
    """A simulation table's values: numbers > 0, numbers >= 0, integers >= 1."""
    for name in positive + not_negative + counts:
        value = getattr(spec, name)
        if name in counts:
            if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise ConfigError(f"{table}: {name} = {value!r} must be a whole number of at least 1")
        elif not _is_number(value) or value < 0 or (name in positive and value == 0):
            raise ConfigError(f"{table}: {name} = {value!r} must be a number {'> 0' if name in positive else '>= 0'}")


@dataclass(frozen=True)
class SimulationSpec:
    plan: Plan = field(default_factory=Plan)
    dut: DutSpec = field(default_factory=DutSpec)
    g_local: float = 9.80101
    g_local_uncertainty: float = 3e-5
    output_unit: str = "bit"
    effects: tuple[tuple[str, tuple[tuple[str, object], ...]], ...] = ()
    foreign: tuple[tuple[str, tuple[tuple[str, object], ...]], ...] = ()
    timebase: TimebaseDefects = field(default_factory=TimebaseDefects)

    def with_timebase(self, text: str) -> SimulationSpec:
        """Time-base defects from ``key=value,...`` (the CLI form)."""
        return replace(self, timebase=TimebaseDefects.parse(text, self.timebase))

    def with_effects(self, *specs: str) -> SimulationSpec:
        return replace(self, effects=self.effects + tuple(parse_effect(s) for s in specs))

    def with_foreign(self, *specs: str) -> SimulationSpec:
        return replace(self, foreign=self.foreign + tuple(parse_effect(s, FOREIGN_NAMES) for s in specs))


@dataclass(frozen=True, eq=False)
class Simulation:
    """Samples with their plan labels, per-segment file names, and the truth."""

    samples: pl.DataFrame
    truth: dict
    dut: Dut
    effects: Effects


def parse_effect(text: str, known: tuple[str, ...] = EFFECT_NAMES) -> tuple[str, tuple[tuple[str, object], ...]]:
    """``NAME:key=value,key=value`` (the CLI form) -> (name, params)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in known:
        raise ConfigError(f"unknown effect {name!r}; known: {', '.join(known)}")
    params = []
    for item in filter(None, (p.strip() for p in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq:
            raise ConfigError(f"effect {name}: {item!r} is not key=value")
        key = key.strip()
        value = value.strip()
        params.append((key, value if key in ("axis", "channel") else _number(name, key, value)))
    return name, tuple(params)


def _number(effect: str, key: str, value: str) -> float:
    try:
        return float(value)
    except ValueError:
        raise ConfigError(f"effect {effect}: {key} = {value!r} is not a number") from None


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


def _effect_params(name: str, params: dict, rng: np.random.Generator) -> dict:
    """Complete one effect's parameters (random where the request leaves a choice)."""
    def need_axis() -> str:
        axis = params.get("axis")
        if axis not in AXES:
            raise ConfigError(f"effect {name} needs axis=x, y or z")
        return axis

    known = {
        "centripetal": {"axis", "radius_m", "d_x_m", "d_y_m", "d_z_m"},
        "cubic_nonlinearity": {"k3_u", "k3_v", "k3_w"},
        "quadratic_nonlinearity": {"k2_u", "k2_v", "k2_w"},
        "clipping": {"clip_low", "clip_high", "below_max", "above_min"},
        "channel_delay": {"delay_v_s", "delay_w_s"},
        "rate_error": {"rate_error"},
        "rate_ripple": {"axis", "ripple_deg", "ripple_phase_deg"},
        "axis_tilt": {"axis", "tilt_deg"},
        "offset_drift": {"drift_u", "drift_v", "drift_w"},
    }[name]
    unknown = sorted(set(params) - known)
    if unknown:
        raise ConfigError(f"effect {name}: unknown parameter {unknown[0]!r} (known: {', '.join(sorted(known))})")
    out = dict(params)
    if name == "centripetal":
        axis = need_axis()
        across = [s for s in AXES if s != axis]
        if "radius_m" in params:
            angle = rng.uniform(0, 2 * np.pi)
            out.update({f"d_{across[0]}_m": params["radius_m"] * np.cos(angle),
                        f"d_{across[1]}_m": params["radius_m"] * np.sin(angle)})
        out.pop(f"d_{axis}_m", None)
        out["radius_m"] = float(np.hypot(out.get(f"d_{across[0]}_m", 0.0), out.get(f"d_{across[1]}_m", 0.0)))
    elif name == "rate_ripple":
        need_axis()
        out.setdefault("ripple_phase_deg", rng.uniform(0, 360))
    elif name == "axis_tilt":
        need_axis()
    return out


def build_effects(requests: tuple, rng: np.random.Generator) -> tuple[Effects, list[dict]]:
    """Effects from requests; clipping limits given as fractions are resolved later."""
    fx: dict = {"centripetal": [], "rate_ripple": [], "axis_tilt": []}
    vec = {"k3": [0.0] * 3, "k2": [0.0] * 3, "delay_s": [0.0] * 3, "drift": [0.0] * 3}
    described = []
    for name, params in requests:
        p = _effect_params(name, dict(params), rng)
        described.append({"effect": name, "axis": p.get("axis", ""), "parameters": {k: v for k, v in p.items() if k != "axis"}})
        if name == "centripetal":
            d = [p.get(f"d_{s}_m", 0.0) for s in AXES]
            fx["centripetal"].append(AxisEffect(p["axis"], tuple(d)))
        elif name == "rate_ripple":
            fx["rate_ripple"].append(AxisEffect(p["axis"], (p.get("ripple_deg", 0.0), p["ripple_phase_deg"])))
        elif name == "axis_tilt":
            fx["axis_tilt"].append(AxisEffect(p["axis"], (p.get("tilt_deg", 0.0),)))
        elif name in ("cubic_nonlinearity", "quadratic_nonlinearity"):
            key = "k3" if name.startswith("cubic") else "k2"
            for r, c in enumerate(CHANNELS):
                vec[key][r] = p.get(f"{key}_{c}", vec[key][r])
        elif name == "channel_delay":
            vec["delay_s"][1:] = [p.get("delay_v_s", 0.0), p.get("delay_w_s", 0.0)]
        elif name == "offset_drift":
            vec["drift"] = [p.get(f"drift_{c}", 0.0) for c in CHANNELS]
        elif name == "rate_error":
            fx["rate_error"] = p.get("rate_error", 0.0)
        elif name == "clipping":
            fx["clip_low"], fx["clip_high"] = p.get("clip_low"), p.get("clip_high")
    effects = Effects(
        centripetal=tuple(fx["centripetal"]), rate_ripple=tuple(fx["rate_ripple"]), axis_tilt=tuple(fx["axis_tilt"]),
        rate_error=fx.get("rate_error", 0.0), clip_low=fx.get("clip_low"), clip_high=fx.get("clip_high"),
        **{k: tuple(v) for k, v in vec.items()},
    )
    return effects, described


def schedule(plan: Plan, rng: np.random.Generator) -> tuple[Motion, pl.DataFrame]:
    """Sample times and commanded motion of the plan, with per-sample labels.

    Per axis: the static steps (logging paused ``step_move_s`` while the table
    moves), then each rate; logging paused ``pause_s`` between segments.
    """
    dt_ns = int(round(plan.dt_s * 1e9))
    parts, t_next, seg = [], 0, 0
    for axis in plan.axes:
        steps = np.arange(0.0, 360.0, plan.step_deg)
        step_start = t_next + np.arange(steps.size) * (plan.step_samples * dt_ns + int(plan.step_move_s * 1e9))
        t = (step_start[:, None] + np.arange(plan.step_samples)[None, :] * dt_ns).ravel()
        parts.append(dict(t_ns=t, axis=axis, rate_hz=0.0, angle=np.repeat(steps, plan.step_samples), theta0=0.0, seg=seg))
        t_next, seg = int(t[-1]) + int(plan.pause_s * 1e9), seg + 1
        for rate in plan.rates_hz:
            t = t_next + np.arange(plan.rotation_samples, dtype=np.int64) * dt_ns
            theta0 = rng.uniform(0.0, 360.0)
            angle = theta0 + 360.0 * rate * (t - t[0]) / 1e9
            parts.append(dict(t_ns=t, axis=axis, rate_hz=rate, angle=angle, theta0=theta0, seg=seg))
            t_next, seg = int(t[-1]) + int(plan.pause_s * 1e9), seg + 1
    sizes = [p["t_ns"].size for p in parts]
    t_ns = np.concatenate([p["t_ns"] for p in parts]).astype(np.int64)
    rate = np.repeat([p["rate_hz"] for p in parts], sizes)
    t_start = np.repeat([p["t_ns"][0] / 1e9 for p in parts], sizes)
    motion = Motion(
        t_s=t_ns / 1e9,
        axis_idx=np.repeat([axis_index(p["axis"]) for p in parts], sizes),
        rotating=rate != 0,
        theta_cmd_deg=np.concatenate([p["angle"] for p in parts]),
        theta0_deg=np.repeat([p["theta0"] for p in parts], sizes),
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
        motion, labels, phases, hand = schedule_continuous(spec.plan, effects.rate_error, plan_rng)
    else:
        motion, labels = schedule(spec.plan, plan_rng)
    clean = noise_free_output(motion, dut, effects, spec.g_local)
    if phases is not None and hand.mask.any():
        # a hand move: the same output chain after r . a (effects.md order) with the hand's specific force
        linear = hand.specific_force(spec.g_local) @ dut.responsivity.T
        x1g = np.linalg.norm(dut.responsivity, axis=1) * spec.g_local
        clean[hand.mask] = dut.offsets + drift_term(motion, effects)[hand.mask] + nonlinearity(linear, x1g, effects)
    effects, described = _resolve_clipping(effects, described, clean)
    clean, foreign = _add_foreign(clean, motion, spec.foreign, effect_rng)
    observed = observe(clean, dut, effects, noise_rng)
    samples = labels.with_columns(
        *(pl.Series(c, observed[:, r]) for r, c in enumerate(CHANNELS))
    ).select("t_ns", *CHANNELS, "axis", "rate_hz", "angle_deg", "plan_segment")
    samples, logger = apply_defects(samples, spec.timebase, logger_rng)
    truth = {
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
    if phases is not None:
        truth["timeline"] = timeline(phases, spec.timebase.clock_factor)
    return Simulation(samples, truth, dut, effects)


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


def _resolve_clipping(effects: Effects, described: list[dict], clean: np.ndarray) -> tuple[Effects, list[dict]]:
    """Clip limits asked for as a fraction below the largest (above the
    smallest) noise-free output become numbers."""
    for d in described:
        if d["effect"] != "clipping":
            continue
        p = d["parameters"]
        high, low = p.get("clip_high"), p.get("clip_low")
        if "below_max" in p:
            peak = float(clean.max())
            high = float(np.floor(peak - p.pop("below_max") * abs(peak)))
        if "above_min" in p:
            trough = float(clean.min())
            low = float(np.ceil(trough + p.pop("above_min") * abs(trough)))
        p.update({k: v for k, v in (("clip_high", high), ("clip_low", low)) if v is not None})
        effects = replace(effects, clip_high=high, clip_low=low)
    return effects, described


def segment_files(samples: pl.DataFrame) -> pl.DataFrame:
    """One CSV file name per plan segment: ``NN_axis_static.csv`` or ``NN_axis_RATEhz.csv``."""
    first = samples.filter(pl.col("plan_segment").is_not_null()).group_by("plan_segment", maintain_order=True).agg(pl.col("axis").first(), pl.col("rate_hz").first())
    names = [
        f"{seg:02d}_{axis}_{'static' if rate == 0 else f'{rate:g}hz'}.csv"
        for seg, axis, rate in first.iter_rows()
    ]
    return first.with_columns(file=pl.Series(names))


def _csv_columns(samples: pl.DataFrame, integer: bool, columns: tuple[str, ...]) -> pl.DataFrame:
    out = samples.with_columns(t=pl.col("t_ns") / 1e9)
    if integer:
        out = out.with_columns(pl.col(c).cast(pl.Int64) for c in CHANNELS)
    return out.select(columns)


def write_csv_segments(sim: Simulation, directory: Path) -> list[Path]:
    """The default layout: one CSV per segment with every label column."""
    files = segment_files(sim.samples)
    written = []
    for seg, name in files.select("plan_segment", "file").iter_rows():
        part = sim.samples.filter(pl.col("plan_segment") == seg)
        path = directory / name
        _csv_columns(part, sim.dut.integer_output, ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg")).write_csv(path)
        written.append(path)
    return written


def write_csv_single(sim: Simulation, path: Path, columns: tuple[str, ...] = ("t", "u", "v", "w")) -> Path:
    """Everything in one CSV, with only ``columns`` (an unlabelled recording)."""
    _csv_columns(sim.samples, sim.dut.integer_output, columns).write_csv(path)
    return path


def table_messages(samples: pl.DataFrame, period_s: float = 0.1) -> pl.DataFrame:
    """What a table controller publishes: at each segment's and step's start
    and last sample, and every ``period_s`` during rotation."""
    frame = samples.with_columns(
        step=pl.struct("plan_segment", pl.when(pl.col("rate_hz") == 0).then(pl.col("angle_deg"))).rle_id()
    )
    edges = frame.filter(pl.col("step").is_first_distinct() | pl.col("step").is_last_distinct())
    tick = ((pl.col("t_ns") - pl.col("t_ns").first().over("plan_segment")) // int(period_s * 1e9))
    ticks = frame.filter((pl.col("rate_hz") != 0) & tick.is_first_distinct().over("plan_segment"))
    return pl.concat([edges, ticks]).unique("t_ns", keep="first").sort("t_ns").select("t_ns", "axis", "rate_hz", "angle_deg")


def write_mcap(sim: Simulation, path: Path, encoding: str = "cdr", imu_topic: str = "/imu",
               table_topic: str = "/table/joint_states") -> Path:
    """One MCAP: the DUT on ``imu_topic`` (Imu in CDR, or JSON with t, u, v, w)
    and the table on ``table_topic`` (JointState in CDR, or JSON).

    A continuous recording has no table messages: the table's messages
    cover the plan's segments only, and a table silent through the
    transitions (step moves, ramps, rests, the hand reorientation) would
    label them as the segment before it (a label holds to the next
    message, contract section 1) and bias every fit they join; its
    segments are found from the signals, as in ``csv-unlabelled``."""
    from rotcal.simulate.mcap_writer import write_capture

    table = table_messages(sim.samples.filter(pl.col("plan_segment").is_not_null()))
    if sim.truth["plan"]["continuous"]:
        table = table.clear()
    return write_capture(sim.samples, table, path, encoding, imu_topic, table_topic)


def write_dataset(sim: Simulation, spec: SimulationSpec, directory: Path, fmt: str = "csv", device_id: str | None = None) -> Path:
    """A dataset directory: captures in ``fmt`` (csv, mcap-cdr, mcap-json),
    ``dataset.toml`` and ``truth.json``."""
    directory.mkdir(parents=True, exist_ok=True)
    if fmt == "csv":
        write_csv_segments(sim, directory)
    elif fmt in ("mcap-cdr", "mcap-json"):
        write_mcap(sim, directory / "capture.mcap", encoding=fmt.split("-")[1])
    elif fmt == "csv-unlabelled":
        write_csv_single(sim, directory / "recording.csv")
    else:
        raise ConfigError(f"unknown format {fmt!r} (csv, csv-unlabelled, mcap-cdr, mcap-json)")
    full_scale = f"full_scale = {spec.dut.full_scale:g}\n" if spec.dut.full_scale else ""
    # a continuous recording comes with the plan's nominal rates, as a lab would write them down
    # (a plan of static steps only has none to write: dataset.toml's rates_hz is never empty)
    plan = f"\n[plan]\nrates_hz = {list(spec.plan.rates_hz)!r}\n" if spec.plan.continuous and spec.plan.rates_hz else ""
    (directory / "dataset.toml").write_text(
        f'[device]\nid = "{device_id or directory.name}"\noutput_unit = "{spec.output_unit}"\n{full_scale}'
        f"\n[site]\ng_local = {spec.g_local!r}\ng_local_uncertainty = {spec.g_local_uncertainty!r}\n{plan}"
    )
    (directory / "truth.json").write_text(json.dumps(sim.truth, indent=2) + "\n")
    return directory


def spec_from_toml(path: Path) -> SimulationSpec:
    """A simulation request file: ``[plan]``, ``[dut]``, ``[site]``,
    ``[timebase]`` tables and ``[[effect]]`` entries (``name`` plus the
    effect's parameters)."""
    import tomllib

    try:
        doc = tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError("simulation file not found", path=path) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"simulation file is not valid TOML: {exc}", path=path) from None
    unknown = sorted(set(doc) - {"plan", "dut", "site", "effect", "output_unit", "timebase"})
    if unknown:
        raise ConfigError(f"unknown table {unknown[0]!r} (plan, dut, site, effect, output_unit, timebase)", path=path)

    def build(cls, table: dict):
        names = set(cls.__dataclass_fields__)
        bad = sorted(set(table) - names)
        if bad:
            raise ConfigError(f"unknown key {bad[0]!r} (known: {', '.join(sorted(names))})", path=path)
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in table.items()})

    site = doc.get("site", {})
    bad_site = sorted(set(site) - {"g_local", "g_local_uncertainty"})
    if bad_site:
        raise ConfigError(f"unknown key {bad_site[0]!r} in [site]", path=path)
    effects = []
    for entry in doc.get("effect", []):
        entry = dict(entry)
        name = entry.pop("name", None)
        if name not in EFFECT_NAMES:
            raise ConfigError(f"[[effect]] name {name!r} is not one of {', '.join(EFFECT_NAMES)}", path=path)
        bad = [k for k, v in entry.items() if k not in ("axis", "channel") and not _is_number(v)]
        if bad:
            raise ConfigError(f"[[effect]] {name}: {bad[0]} = {entry[bad[0]]!r} is not a number", path=path)
        effects.append((name, tuple(sorted(entry.items()))))
    try:
        plan, dut = build(Plan, doc.get("plan", {})).checked(), build(DutSpec, doc.get("dut", {})).checked()
    except ConfigError as exc:
        raise ConfigError(exc.problem, path=path) from None
    return SimulationSpec(
        plan=plan,
        dut=dut,
        g_local=site.get("g_local", 9.80101),
        g_local_uncertainty=site.get("g_local_uncertainty", 3e-5),
        output_unit=doc.get("output_unit", "bit"),
        effects=tuple(effects),
        timebase=build(TimebaseDefects, doc.get("timebase", {})).checked(),
    )
