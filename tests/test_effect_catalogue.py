"""The effect catalogue (rotcal.model.effects): one definition per effect,
read by the simulator, the forward model and the diagnosis. A new effect,
defined here and added through the registry only, is accepted by the
simulator, applied by the forward model and found by the diagnosis."""

import json

import numpy as np
import polars as pl
import pytest

from rotcal.config import RunConfig, RunSection
from rotcal.diagnose.candidates import extensions
from rotcal.diagnose.scenarios import draw_effect
from rotcal.errors import ConfigError
from rotcal.model.conventions import CHANNELS
from rotcal.model.effects import Effects, catalogue, effect_named, listed, names, registered, table
from rotcal.model.effects.base import Candidate, OffsetEffect, Parameter
from rotcal.model.physics import noise_free_output
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, build_effects, schedule, simulate, spec_from_toml, write_dataset

TABLE_ORDER = ("centripetal", "cubic_nonlinearity", "quadratic_nonlinearity", "clipping", "channel_delay",
               "rate_error", "rate_ripple", "axis_tilt", "offset_drift", "thermal")
FORWARD_ORDER = ("rate_error", "rate_ripple", "channel_delay", "axis_tilt", "centripetal", "cubic_nonlinearity",
                 "quadratic_nonlinearity", "thermal", "offset_drift", "clipping")


class OffsetWobble(OffsetEffect):
    """A demonstration effect: each offset swings with a 600 s period,
    O_r -> O_r + b_r sin(2 pi t / 600 s). Everything rotcal needs of it is
    here: nothing else is edited to add it."""

    name = "offset_wobble"
    physics = "offsets swing slowly: O_r -> O_r + b_r sin(2 pi (t - t0) / 600 s)"
    parameters = tuple(Parameter(f"wobble_{c}", "output unit", f"amplitude b of {c}") for c in CHANNELS)
    options = frozenset(p.name for p in parameters)
    sizes = (2.0, 10.0)
    size_of = "abs(b) on one channel"
    where = "channel {s}, whole recording"
    listed = 10

    def state(self, previous, params):
        return np.asarray([params.get(f"wobble_{c}", 0.0) for c in CHANNELS], float)

    def offset(self, state, motion):
        return state[None, :] * self._wave(motion)[:, None]

    @staticmethod
    def _wave(motion):
        return np.sin(2 * np.pi * (motion.t_s - motion.t0_s) / 600.0)

    def draw(self, size, sign, axis, channel, rng):
        return f"offset_wobble:wobble_{channel}={sign * size:.6g}"

    def candidates(self, rotating_axes, all_axes, angles_measured):
        return tuple(Candidate(self.name, c, (f"wobble_{c}",), ((r,),)) for r, c in enumerate(CHANNELS))

    def state_from(self, values):
        keys = [f"wobble_{c}" for c in CHANNELS]
        return np.array([float(values.get(k, 0.0)) for k in keys]) if any(k in values for k in keys) else None

    def column(self, name, cand, st, ctx, out=None):
        return ctx.cached(self.name, lambda: self._wave(ctx.motion))


def test_the_catalogue_holds_each_effect_once_in_both_orders():
    assert names() == TABLE_ORDER == tuple(e.name for e in listed())
    assert tuple(e.name for e in catalogue()) == FORWARD_ORDER
    for effect in catalogue():
        assert effect.parameters and effect.physics and effect.where and effect.sizes[0] < effect.sizes[1]
        assert effect_named(effect.name) is effect
    with pytest.raises(ConfigError, match="unknown effect 'wobble'"):
        effect_named("wobble")


def test_the_catalogue_table_lists_every_parameter_with_its_unit_and_sizes():
    rows = table().splitlines()[2:]
    assert [r.split("`")[1] for r in rows] == list(TABLE_ORDER)
    assert all(r.count("|") == 5 for r in rows)
    assert "`tilt_deg` (degree)" in rows[7] and rows[7].endswith(": 0.08 to 0.5 |")


@pytest.mark.parametrize("name", TABLE_ORDER)
def test_every_drawn_scenario_is_an_option_the_simulator_accepts(name):
    """The sizes of docs/effects.md, drawn as ``NAME:key=value``, parsed and built."""
    option = draw_effect(name, np.random.default_rng(3))
    spec = SimulationSpec().with_effects(option)
    effects, described = build_effects(spec.effects, np.random.default_rng(0))
    assert list(effects.states) == [name] and described[0]["effect"] == name


def test_an_unknown_parameter_names_the_known_ones():
    spec = SimulationSpec().with_effects("axis_tilt:axis=x,tilt=0.3")
    with pytest.raises(ConfigError, match=r"unknown parameter 'tilt' \(known: axis, tilt_deg\)"):
        build_effects(spec.effects, np.random.default_rng(0))


def test_a_new_effect_is_one_definition(tmp_path):
    """Registered, the demonstration effect is a simulator option (CLI form
    and TOML), a term of the forward model, a set of extensions the
    diagnosis tests, and a named finding with its parameter measured;
    unregistered, it is gone."""
    with registered(OffsetWobble()):
        assert names()[-1] == "offset_wobble" and catalogue()[-2].name == "offset_wobble"  # offsets, before limits
        toml = tmp_path / "sim.toml"
        toml.write_text('[[effect]]\nname = "offset_wobble"\nwobble_v = 12.0\n')
        assert spec_from_toml(toml).effects == (("offset_wobble", (("wobble_v", 12.0),)),)

        spec = SimulationSpec().with_effects("offset_wobble:wobble_v=12")
        sim = simulate(spec, 7)
        assert sim.truth["effects"] == [{"effect": "offset_wobble", "axis": "", "parameters": {"wobble_v": 12.0}}]
        motion, _ = schedule(spec.plan, np.random.default_rng(1))
        change = noise_free_output(motion, sim.dut, sim.effects, 9.8) - noise_free_output(motion, sim.dut, Effects(), 9.8)
        np.testing.assert_allclose(change[:, 1], 12.0 * OffsetWobble._wave(motion), atol=1e-9)
        assert np.abs(change[:, [0, 2]]).max() < 1e-9

        assert [c.key for c in extensions(("x",), ("x",), False)][-3:] == [f"offset_wobble@{c}" for c in CHANNELS]

        data = write_dataset(sim, spec, tmp_path / "data")
        run_dataset(data, tmp_path / "out", config=RunConfig(run=RunSection(workers=1)))
        findings = pl.read_parquet(tmp_path / "out" / "diagnosis.parquet")
        assert findings.height == 10 and findings["effect"][-1] == "offset_wobble"
        assert set(findings.filter(pl.col("detected"))["effect"]) == {"offset_wobble"}
        assert findings.filter(pl.col("effect") == "offset_wobble")["where"].item() == "channel v, whole recording"
        row = pl.read_parquet(tmp_path / "out" / "effect_parameters.parquet").row(0, named=True)
        assert (row["parameter"], row["unit"]) == ("wobble_v", "bit")
        truth = json.loads((data / "truth.json").read_text())["effects"][0]["parameters"]["wobble_v"]
        assert abs(row["value"] - truth) <= 3 * row["std_uncertainty"]
    assert "offset_wobble" not in names()
    with pytest.raises(ConfigError, match="unknown effect 'offset_wobble'"):
        SimulationSpec().with_effects("offset_wobble:wobble_v=12")


@pytest.mark.parametrize(("request_text", "message"), [
    ("channel_delay", "give its size, one of delay_v_s, delay_w_s"),
    ("axis_tilt:axis=x", "give its size, one of tilt_deg"),
    ("rate_ripple:axis=y,ripple_phase_deg=30", "give its size, one of ripple_deg"),
    ("centripetal:axis=x,radius_m=-5", "radius_m = -5.0 is a magnitude and cannot be negative"),
    ("clipping:below_max=-0.01", "below_max = -0.01 is a magnitude and cannot be negative"),
])
def test_an_effect_without_its_size_or_with_a_negative_magnitude_is_refused(request_text, message):
    """Asked for with no size it would be simulated as absent; a negative
    radius was silently taken as its absolute value."""
    with pytest.raises(ConfigError, match=message):
        build_effects(SimulationSpec().with_effects(request_text).effects, np.random.default_rng(1))
