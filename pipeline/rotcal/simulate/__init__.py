"""The simulator: a test plan, a DUT drawn at random, any effect of the
catalogue switched on, logger defects; seeded and deterministic
(``simulate``), written as CSV or MCAP (``write_dataset``). Callers import
the simulator's names from here."""

from __future__ import annotations

from rotcal.simulate.core import build_effects, draw_dut, schedule, simulate
from rotcal.simulate.spec import DutSpec, Plan, Simulation, SimulationSpec, spec_from_toml
from rotcal.simulate.writers import segment_files, table_messages, write_csv_segments, write_csv_single, write_dataset, write_mcap

__all__ = ["DutSpec", "Plan", "Simulation", "SimulationSpec", "build_effects", "draw_dut", "schedule", "segment_files",
           "simulate", "spec_from_toml", "table_messages", "write_csv_segments", "write_csv_single", "write_dataset",
           "write_mcap"]
