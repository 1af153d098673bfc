"""Issue 16, item 1: captures reduced and written in bounded memory.

The streamed simulator must write the very bytes the in-memory one does
(the same random streams drawn in blocks), and the per-segment normal
equations accumulated chunk by chunk must give the in-memory fit."""

from __future__ import annotations

from dataclasses import replace

import pytest

from rotcal.simulate import SimulationSpec, simulate, write_dataset
from rotcal.simulate.streamed import streamable, write_streamed


def small_spec() -> SimulationSpec:
    spec = SimulationSpec()
    return replace(spec, plan=replace(spec.plan, rotation_samples=2500, rates_hz=(0.05, 0.5)))


@pytest.mark.parametrize("block", [1000, 1 << 20])
def test_streamed_simulation_writes_the_same_bytes(tmp_path, block):
    """Blocks of 1000 samples split every rotation (2500 samples) and the
    static sequences (1200) mid-way; one large block holds each segment whole."""
    spec = small_spec()
    assert streamable(spec, "mcap-cdr")
    memory = write_dataset(simulate(spec, 7), spec, tmp_path / "memory", "mcap-cdr", "dut")
    streamed = write_streamed(spec, 7, tmp_path / "streamed", "dut", block=block)
    for name in ("capture.mcap", "truth.json", "dataset.toml"):
        assert (streamed / name).read_bytes() == (memory / name).read_bytes(), name


def test_only_plain_plans_are_streamed():
    spec = small_spec()
    assert not streamable(spec, "csv")
    assert not streamable(spec.with_effects("centripetal:axis=x,radius_m=0.2"), "mcap-cdr")
    assert not streamable(spec.with_timebase("drop_fraction=0.01"), "mcap-cdr")
    assert not streamable(replace(spec, plan=replace(spec.plan, continuous=True)), "mcap-cdr")
