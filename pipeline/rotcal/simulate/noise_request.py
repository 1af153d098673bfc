"""A noise request of the simulator, from the CLI form ``key=value,...``
or a simulation file's ``[noise]`` table: a preset's name (a sensor class of
``noise_presets``) and values of ``NoiseSpec`` keys over it, resolved in
counts for the DUT and sample rate when the dataset is drawn."""

from __future__ import annotations

from dataclasses import fields, replace

from rotcal.errors import ConfigError
from rotcal.simulate.noise import NoiseSpec
from rotcal.simulate.noise_presets import preset


def parse_noise(text: str) -> tuple[str, tuple[tuple[str, object], ...]]:
    """``key=value,...`` (the CLI form) -> (preset name, the keys' values),
    checked: numbers for the scalar keys, ``ar=0.5;0.2`` coefficients,
    ``gauss_markov=100:2;1000:1`` tau_s:sd terms, ``preset=NAME`` a sensor
    class of ``noise_presets`` whose figures the keys then change."""
    kinds = {f.name for f in fields(NoiseSpec)}
    name, values = "", dict[str, object]()
    for item in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = (s.strip() for s in item.partition("="))
        if not eq or key not in kinds | {"preset"}:
            raise ConfigError(f"noise: {item!r} is not key=value with a key of preset, {', '.join(sorted(kinds))}")
        try:
            if key == "preset":
                name = value
            elif key == "ar":
                values[key] = tuple(float(v) for v in value.split(";") if v.strip())
            elif key == "gauss_markov":
                values[key] = tuple(tuple(float(x) for x in term.split(":")) for term in value.split(";") if term.strip())
            elif key == "lowpass_order":
                values[key] = int(value)
            else:
                values[key] = float(value)
        except ValueError:
            raise ConfigError(f"noise: {key} = {value!r} is not a number (lists: ar=0.5;0.2, gauss_markov=100:2;1000:1)") from None
    return checked_request(name, tuple(values.items()))


def checked_request(name: str, values: tuple[tuple[str, object], ...]) -> tuple[str, tuple[tuple[str, object], ...]]:
    """A noise request (preset name, key values) with its name known and
    its values ones a spec can have (checked over the preset at 1 count per
    m/s^2 and 100 Hz: a preset's figures are resolved for the DUT later)."""
    if name:
        preset(name)
    known = {f.name for f in fields(NoiseSpec)}
    bad = sorted(k for k, _ in values if k not in known)
    if bad:
        raise ConfigError(f"noise: unknown key {bad[0]!r} (known: preset, {', '.join(sorted(known))})")
    resolve_noise(name, values, 1.0, 100.0)
    return name, values


def from_table(table: dict) -> tuple[str, tuple[tuple[str, object], ...]]:
    """A ``[noise]`` table of a simulation file (``preset`` plus any key of
    ``NoiseSpec``, lists as TOML arrays) as a checked noise request."""
    table = dict(table)
    name = table.pop("preset", "")
    if not isinstance(name, str):
        raise ConfigError(f"noise: preset = {name!r} must be a name")
    if "ar" in table and isinstance(table["ar"], list):
        table["ar"] = tuple(table["ar"])
    if "gauss_markov" in table and isinstance(table["gauss_markov"], list):
        table["gauss_markov"] = tuple(tuple(t) if isinstance(t, list) else t for t in table["gauss_markov"])
    return checked_request(name, tuple(sorted(table.items())))


def resolve_noise(name: str, values: tuple[tuple[str, object], ...], counts_per_ms2: float,
                  fs_hz: float) -> NoiseSpec:
    """The noise of a request for a DUT of ``counts_per_ms2`` sampled at
    ``fs_hz``: the preset's figures in counts (none: no noise), changed by
    the request's values."""
    base = preset(name).in_counts(counts_per_ms2, fs_hz) if name else NoiseSpec()
    changes: dict = dict(values)
    try:
        return replace(base, **changes).checked()
    except TypeError as exc:
        raise ConfigError(f"noise: {exc}") from None
