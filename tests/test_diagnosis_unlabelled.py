"""The diagnosis of recordings without table angles (issue 15 item 1):
t, u, v, w only, no [plan] rates; the angles reconstructed from the
phase-free solution against the simulator's true angles, a clean recording
without findings, and an effect that turns the channels' phases (the
hardest for the reconstruction) found and measured. The full-size figures
come from scripts/unlabelled_diagnosis_acceptance.py."""

import json
from dataclasses import replace

import polars as pl
import pytest

from rotcal.combine.unreferenced import segment_phases
from rotcal.config import RunConfig, RunSection
from rotcal.diagnose.reconstructed import with_reconstructed_angles
from rotcal.ingest.dataset import load_dataset
from rotcal.run import run_dataset
from rotcal.run.stages import segment_and_fit
from rotcal.simulate import SimulationSpec, simulate, write_dataset

ONE_WORKER = RunConfig(run=RunSection(workers=1))


def _unlabelled(tmp_path, seed, effects=(), spec=SimulationSpec()):
    """An unlabelled recording (the default plan) without its nominal rates, and its simulation."""
    spec = spec.with_effects(*effects)
    sim = simulate(spec, seed)
    data = write_dataset(sim, spec, tmp_path / "data", "csv-unlabelled")
    toml = data / "dataset.toml"
    toml.write_text(toml.read_text().split("\n[plan]")[0])
    return data, sim


def _run(tmp_path, seed, effects=()):
    data, _ = _unlabelled(tmp_path, seed, effects)
    outcome = run_dataset(data, tmp_path / "out", config=ONE_WORKER)
    truth = json.loads((data / "truth.json").read_text())
    findings = pl.read_parquet(tmp_path / "out" / "diagnosis.parquet")
    params = pl.read_parquet(tmp_path / "out" / "effect_parameters.parquet")
    return outcome, truth, findings, params


def test_reconstructed_angles_are_the_table_angles(tmp_path):
    """theta = sigma_k (theta_k + phi) of every rotation sample against the
    simulator's commanded angle: equal within a few hundredths of a degree
    (the phase-free solution's uncertainty), both senses of rotation."""
    spec = SimulationSpec()
    data, sim = _unlabelled(tmp_path, 41, spec=replace(spec, plan=replace(spec.plan, rates_hz=(0.05, -0.1, 0.5))))
    ds = load_dataset(data, None, ONE_WORKER.limits, 1)
    seg = segment_and_fit(ds, ONE_WORKER)
    phases = segment_phases(seg.fits, seg.segments, seg.own_phase, ds.meta.g_local, ds.meta.g_local_uncertainty, 1.0)
    assert phases.height == 9 and (phases["sigma"] == -1).sum() == 3 and (phases["theta_k_u_deg"] < 0.05).all()
    samples, _ = with_reconstructed_angles(seg.samples, seg.segments, phases)
    rebuilt = samples.filter(pl.col("segment").is_in(phases["segment"].implode())).select("t_ns", "angle_deg", "axis")
    true = rebuilt.join(sim.samples.select("t_ns", true_deg="angle_deg", true_axis="axis", true_rate="rate_hz"), on="t_ns")
    assert true.height == rebuilt.height > 35000
    assert (true["axis"] == true["true_axis"]).all() and (true["true_rate"] != 0).all()
    error = (true["angle_deg"] - true["true_deg"] + 180.0) % 360.0 - 180.0
    assert error.abs().max() < 0.1, error.abs().max()


def test_clean_unlabelled_recording_has_no_finding(tmp_path):
    outcome, _, findings, params = _run(tmp_path, 42)
    assert not findings["detected"].any(), findings.filter(pl.col("detected"))
    assert params.height == 0
    # the angles absorb a rate error: listed as not testable, never tested
    rate_error = findings.row(by_predicate=pl.col("effect") == "rate_error", named=True)
    assert rate_error["where"] == "not testable here" and rate_error["p_value"] == 1.0
    assert set(findings["effect"]) >= {"channel_delay", "rate_ripple", "axis_tilt", "centripetal", "offset_drift"}
    assert any("reconstructed from the solved phases of 12 rotation segment(s)" in n for n in outcome.notes)


@pytest.mark.parametrize("effect, parameter, value", [
    ("channel_delay:delay_w_s=0.003", "delay_w_s", 0.003),
    ("centripetal:axis=z,radius_m=0.06", "radius_m", 0.06),
])
def test_effect_in_unlabelled_recording_is_named_and_measured(tmp_path, effect, parameter, value):
    """A channel delay turns one channel's phase, which biases the phase-free
    theta_k: measured within 3u only with the phases solved jointly with it."""
    _, _, findings, params = _run(tmp_path, 43, (effect,))
    name = effect.split(":")[0]
    assert set(findings.filter(pl.col("detected"))["effect"]) == {name}
    row = params.row(by_predicate=pl.col("parameter") == parameter, named=True)
    assert abs(row["value"] - value) < 3 * row["std_uncertainty"], row
