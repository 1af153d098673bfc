"""The simulator's request: the test plan of Gaitan & Geist 2021 (the
defaults of ``Plan``), how the DUT is drawn, the site, the
effects of the catalogue (``rotcal.model.effects``) and structures outside
it, and the logger's time-base defects; from the CLI form
``NAME:key=value`` or from a simulation TOML file."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import read_toml
from rotcal.errors import ConfigError
from rotcal.model.conventions import AXES, Dut
from rotcal.model.effects import Effects, effect_named, names
from rotcal.simulate.noise_request import from_table, parse_noise
from rotcal.simulate.timebase_sim import TimebaseDefects

# Structures outside the catalogue of docs/effects.md, for testing that rotcal
# reports them as unexplained instead of forcing them onto a catalogue name.
FOREIGN_NAMES = ("tone", "offset_step")

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
        if not isinstance(self.axes, tuple) or not self.axes or any(a not in AXES for a in self.axes):
            axes = list(self.axes) if isinstance(self.axes, tuple) else self.axes  # a number is no list to show
            raise ConfigError(f"plan: axes = {axes!r} must be a non-empty list of x, y, z")
        _require(self, "plan", positive=("step_deg", "dt_s", "ramp_deg_s2"),
                 not_negative=("pause_s", "step_move_s", "reorient_s"), counts=("step_samples", "rotation_samples"))
        if self.dt_s < 1e-9:  # stamps are whole nanoseconds: a shorter interval rounds to 0 and divides by it
            raise ConfigError(f"plan: dt_s = {self.dt_s!r} must be at least 1e-9 s")
        if not isinstance(self.rates_hz, tuple) or not all(_is_number(f) for f in self.rates_hz):
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
    """A finite float, or an integer within TOML's 64 bits (np.isfinite refuses larger ones with a TypeError)."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    return math.isfinite(value) if isinstance(value, float) else -(2**63) <= value < 2**63


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
    # the DUT's noise beyond white (``simulate.noise``): a preset's name and key values over it;
    # none: white noise of ``dut.noise_std``
    noise: tuple[str, tuple[tuple[str, object], ...]] = ("", ())

    def with_noise(self, text: str) -> SimulationSpec:
        """The noise from ``key=value,...`` (the CLI form, ``simulate.noise_request.parse_noise``)."""
        return replace(self, noise=parse_noise(text))

    def with_timebase(self, text: str) -> SimulationSpec:
        """Time-base defects from ``key=value,...`` (the CLI form)."""
        return replace(self, timebase=key_values(self.timebase, text, "timebase"))

    def with_plan(self, text: str) -> SimulationSpec:
        """The plan's numbers from ``key=value,...`` (the CLI form), e.g.
        ``step_move_s=0,dt_s=0.05``: steps faster than a sample at 20 Hz."""
        return replace(self, plan=key_values(self.plan, text, "plan"))

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
    # what a table controller publishes (``writers.table_messages``), stamped
    # by its own clock at the instants of the samples before the logger's
    # defects: a controller's stamps owe nothing to the DUT's jitter
    table: pl.DataFrame


def key_values(base, text: str, table: str):
    """``base`` (a plan or time-base dataclass) with the numbers of
    ``key=value,key=value`` (the CLI form), checked; lists and names are
    given in a simulation file."""
    kinds = {f.name: f.type for f in fields(base) if f.type in ("int", "float", "bool")}
    values: dict[str, object] = {}
    for item in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = item.partition("=")
        key, value = key.strip(), value.strip()
        if not eq or key not in kinds:
            raise ConfigError(f"{table}: {item!r} is not key=value with a key of {', '.join(kinds)}")
        if kinds[key] == "bool":
            if value not in ("true", "false"):
                raise ConfigError(f"{table}: {key} = {value!r} is not true or false")
            values[key] = value == "true"
            continue
        try:
            values[key] = int(value) if kinds[key] == "int" else float(value)
        except ValueError:
            raise ConfigError(f"{table}: {key} = {value!r} is not a number") from None
    return replace(base, **values).checked()


def parse_effect(text: str, known: tuple[str, ...] | None = None) -> tuple[str, tuple[tuple[str, object], ...]]:
    """``NAME:key=value,key=value`` (the CLI form) -> (name, params); the
    names known are the catalogue's unless given."""
    name, _, rest = text.partition(":")
    name = name.strip()
    known = names() if known is None else known
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


def spec_from_toml(path: Path) -> SimulationSpec:
    """A simulation request file: ``[plan]``, ``[dut]``, ``[site]``,
    ``[timebase]``, ``[noise]`` tables and ``[[effect]]`` entries (``name`` plus the
    effect's parameters)."""
    doc = read_toml(path, "simulation file")
    unknown = sorted(set(doc) - {"plan", "dut", "site", "effect", "output_unit", "timebase", "noise"})
    if unknown:
        raise ConfigError(f"unknown table {unknown[0]!r} (plan, dut, site, effect, output_unit, timebase, noise)", path=path)

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
    not_numbers = [k for k, v in site.items() if not _is_number(v) or v < 0]
    if not_numbers:
        raise ConfigError(f"[site] {not_numbers[0]} = {site[not_numbers[0]]!r} must be a finite number >= 0", path=path)
    effects = []
    for entry in doc.get("effect", []):
        entry = dict(entry)
        name = entry.pop("name", None)
        if name not in names():
            raise ConfigError(f"[[effect]] name {name!r} is not one of {', '.join(names())}", path=path)
        bad = [k for k, v in entry.items() if k not in ("axis", "channel") and not _is_number(v)]
        if bad:
            raise ConfigError(f"[[effect]] {name}: {bad[0]} = {entry[bad[0]]!r} is not a number", path=path)
        try:  # the effect's own check of its parameters, here where the file is known
            effect_named(name).complete(dict(entry), np.random.default_rng(0))
        except ConfigError as exc:
            raise ConfigError(exc.problem, path=path) from None
        effects.append((name, tuple(sorted(entry.items()))))
    try:
        plan, dut = build(Plan, doc.get("plan", {})).checked(), build(DutSpec, doc.get("dut", {})).checked()
        timebase = build(TimebaseDefects, doc.get("timebase", {})).checked()
        noise = from_table(doc.get("noise", {}))
    except ConfigError as exc:
        raise ConfigError(exc.problem, path=path) from None
    return SimulationSpec(
        plan=plan,
        dut=dut,
        g_local=site.get("g_local", 9.80101),
        g_local_uncertainty=site.get("g_local_uncertainty", 3e-5),
        output_unit=doc.get("output_unit", "bit"),
        effects=tuple(effects),
        timebase=timebase,
        noise=noise,
    )
