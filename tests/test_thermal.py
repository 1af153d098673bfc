"""The tenth catalogue effect, ``thermal`` (issue 15 item 3): offsets and
sensitivities that follow the DUT temperature, O_r -> O_r + tco_r (T -
T_ref), s_r -> s_r (1 + tcs_r (T - T_ref)); the simulator draws a warm-up
and writes ``temperature_c``; the diagnosis tests it only where the dataset
logs a varying temperature, and tells it from ``offset_drift`` by the
warm-up's shape."""

import dataclasses
import json

import numpy as np
import polars as pl
import pytest

from rotcal.config import RunConfig, RunSection
from rotcal.diagnose.candidates import extensions
from rotcal.errors import ConfigError
from rotcal.model.conventions import Dut, Motion
from rotcal.model.effects import Effects, effect_named
from rotcal.model.physics import noise_free_output
from rotcal.run import run_dataset
from rotcal.simulate import SimulationSpec, build_effects, simulate, write_dataset

THERMAL = "thermal:tco_v=1.5,tcs_v=6e-5,warmup_k=6,tau_frac=0.25"


def _motion(temperature):
    n = len(temperature)
    return Motion(t_s=np.arange(n, dtype=float), axis_idx=np.array([0, 0, 1, 2]), rotating=np.zeros(n, bool),
                  theta_cmd_deg=np.array([0.0, 90.0, 180.0, 30.0]), t_start_s=np.zeros(n),
                  rate_hz=np.zeros(n), temperature_c=np.asarray(temperature, float))


def test_the_forward_model_adds_the_offset_term_and_scales_the_sensitivity():
    """Hand-derived on four samples: T = 20, 22, 25, 29 (T_ref = 24); the
    static angles 0, 90 deg about x, 180 deg about y, 30 deg about z give
    gravity (0, 0, 1), (0, -1, 0), (0, 0, -1) and (-sin 30, cos 30, 0)
    (Geist Eq. 5, docs/conventions.md)."""
    motion = _motion([20.0, 22.0, 25.0, 29.0])
    dut = Dut(np.diag([100.0, 200.0, 300.0]), np.array([5.0, -7.0, 11.0]), np.zeros(3))
    state = np.array([[0.5, -2.0, 0.0], [1e-3, 0.0, -2e-3]])   # (tco, tcs) per channel
    out = noise_free_output(motion, dut, Effects({"thermal": state}), 1.0)
    dT = np.array([-4.0, -2.0, 1.0, 5.0])
    force = np.array([[0, 0, 1], [0, -1, 0], [0, 0, -1], [-0.5, np.cos(np.pi / 6), 0]])
    y = force * np.array([100.0, 200.0, 300.0])
    expected = (np.array([5.0, -7.0, 11.0]) + np.outer(dT, [0.5, -2.0, 0.0])
                + y * (1 + np.outer(dT, [1e-3, 0.0, -2e-3])))
    np.testing.assert_allclose(out, expected, atol=1e-12)
    # by hand: u at sample 3 is 5 + 0.5 * 5 + 100 * (-0.5) * (1 + 1e-3 * 5); v at sample 1 is -7 + 4 - 200
    assert out[3, 0] == pytest.approx(7.5 - 50.25) and out[1, 1] == pytest.approx(-203.0)
    np.testing.assert_array_equal(noise_free_output(motion, dut, Effects({"thermal": np.zeros((2, 3))}), 1.0),
                                  noise_free_output(motion, dut, Effects(), 1.0))


def test_the_thermal_term_needs_a_temperature():
    motion = dataclasses.replace(_motion([20.0] * 4), temperature_c=None)
    dut = Dut(np.eye(3), np.zeros(3), np.zeros(3))
    with pytest.raises(ConfigError, match="temperature_c"):
        noise_free_output(motion, dut, Effects({"thermal": np.ones((2, 3))}), 1.0)


def test_the_simulator_writes_an_exponential_warm_up_of_the_requested_size(tmp_path):
    spec = SimulationSpec().with_effects(THERMAL + ",start_c=21.5")
    sim = simulate(spec, 3)
    t = sim.samples["t_ns"].to_numpy() / 1e9
    T = sim.samples["temperature_c"].to_numpy()
    duration = t[-1] - t[0]
    np.testing.assert_allclose(T, 21.5 + 6.0 * (1 - np.exp(-(t - t[0]) / (0.25 * duration))), atol=1e-9)
    assert T[-1] - T[0] == pytest.approx(6.0 * (1 - np.exp(-4.0)))
    assert sim.truth["effects"][0]["parameters"] == {"tco_v": 1.5, "tcs_v": 6e-5, "warmup_k": 6.0, "tau_frac": 0.25,
                                                     "start_c": 21.5, "step_k": 0.0}
    data = write_dataset(sim, spec, tmp_path / "data")
    written = pl.concat([pl.read_csv(p) for p in sorted(data.glob("*.csv"))])
    np.testing.assert_allclose(written["temperature_c"].to_numpy(), T)
    # without the effect nothing is logged: the files are as before
    assert "temperature_c" not in simulate(SimulationSpec(), 3).samples.columns


def test_a_drawn_history_lies_in_the_stated_ranges_and_a_step_is_where_asked():
    effects, described = build_effects(SimulationSpec().with_effects("thermal:tco_u=1").effects, np.random.default_rng(5))
    p = described[0]["parameters"]
    assert 3 <= p["warmup_k"] <= 8 and 0.1 <= p["tau_frac"] <= 0.4 and 20 <= p["start_c"] <= 25 and p["step_k"] == 0
    np.testing.assert_array_equal(effects.states["thermal"], [[1, 0, 0], [0, 0, 0]])
    sim = simulate(SimulationSpec().with_effects("thermal:tco_w=1,warmup_k=0,step_k=-2,step_frac=0.5,start_c=24"), 1)
    t, T = sim.samples["t_ns"].to_numpy() / 1e9, sim.samples["temperature_c"].to_numpy()
    after = t - t[0] >= 0.5 * (t[-1] - t[0])
    assert set(T[~after]) == {24.0} and set(T[after]) == {22.0}
    with pytest.raises(ConfigError, match="give its size"):
        build_effects(SimulationSpec().with_effects("thermal:warmup_k=5").effects, np.random.default_rng(0))


def test_the_diagnosis_tests_it_only_where_temperature_is_logged():
    assert not any(c.effect == "thermal" for c in extensions(("x",), ("x",), False))
    keys = [c.key for c in extensions(("x",), ("x",), False, frozenset({"temperature_c"}))]
    assert keys[-3:] == ["thermal@u", "thermal@v", "thermal@w"]
    assert effect_named("thermal").needs == {"temperature_c"}


def _diagnose(tmp_path, sim, spec):
    data = write_dataset(sim, spec, tmp_path / "data")
    run_dataset(data, tmp_path / "out", config=RunConfig(run=RunSection(workers=1)))
    findings = pl.read_parquet(tmp_path / "out" / "diagnosis.parquet")
    params = pl.read_parquet(tmp_path / "out" / "effect_parameters.parquet")
    return findings, params, json.loads((data / "truth.json").read_text())


def _warm_up_case(tmp_path, seed):
    """A table recording with an exponential warm-up (tco_v = 1.5 bit/K,
    6 K, tau 25 % of the session): (named alone, tco_v within 3u)."""
    spec = SimulationSpec().with_effects(THERMAL)
    findings, params, _ = _diagnose(tmp_path / str(seed), simulate(spec, seed), spec)
    named = set(findings.filter(pl.col("detected"))["effect"])
    row = params.filter(pl.col("parameter") == "tco_v")
    within = row.height == 1 and abs(row["value"].item() - 1.5) <= 3 * row["std_uncertainty"].item()
    return named == {"thermal"}, within


def test_a_warm_up_is_named_thermal_not_offset_drift(tmp_path):
    for seed in (1, 2):
        named, within = _warm_up_case(tmp_path, seed)
        assert named and within, seed


@pytest.mark.slow
def test_a_warm_up_is_named_thermal_in_at_least_8_of_10_seeds(tmp_path):
    cases = [_warm_up_case(tmp_path, seed) for seed in range(10, 20)]
    assert sum(named for named, _ in cases) >= 8
    assert sum(within for _, within in cases) >= 6


@pytest.mark.parametrize("temperature", ["constant", "absent"])
def test_offset_drift_without_a_varying_temperature_is_not_thermal(tmp_path, temperature):
    spec = SimulationSpec().with_effects("offset_drift:drift_w=0.02")
    sim = simulate(spec, 4)
    if temperature == "constant":
        sim = dataclasses.replace(sim, samples=sim.samples.with_columns(temperature_c=pl.lit(23.0)))
    findings, _, _ = _diagnose(tmp_path, sim, spec)
    assert set(findings.filter(pl.col("detected"))["effect"]) == {"offset_drift"}
    assert "thermal" not in findings["effect"].to_list()


def test_offset_drift_during_a_logged_warm_up_is_not_thermal(tmp_path):
    """A linear drift while the logged temperature warms up exponentially
    (the DUT itself insensitive to it): the shapes differ, drift wins."""
    spec = SimulationSpec().with_effects("offset_drift:drift_w=0.02", "thermal:tco_w=0,warmup_k=6,tau_frac=0.25")
    findings, _, _ = _diagnose(tmp_path, simulate(spec, 4), spec)
    assert set(findings.filter(pl.col("detected"))["effect"]) == {"offset_drift"}
    assert not findings.filter(pl.col("effect") == "thermal")["detected"].item()
