"""Simulate a capture of any length in bounded memory: the plan's segments
generated one after another, each in blocks of ``BLOCK_SAMPLES`` samples
(commanded motion, the forward model of ``model.physics``, the noise), and
handed to the MCAP writer block by block (``mcap_writer.write_cdr_blocks``).

The random streams are those of ``core.simulate`` drawn in the same order
(numpy's generators give the same numbers drawn in blocks as at once), so
the file is byte for byte the one ``simulate`` + ``write_dataset`` write.
It covers what a long capture needs: the plan of static steps and constant
rotations with the DUT's noise, written as an MCAP CDR capture. Effects,
foreign structures, logger defects, coloured noise and the continuous plan act on the whole
recording at once (a clip limit from the largest output, a temperature
history, dropped samples): those are simulated in memory.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.ingest.formats.mcap.writer import write_cdr_blocks
from rotcal.model.physics import Dut, Effects, Motion, axis_index, noise_free_output, observe
from rotcal.simulate.core import build_effects, draw_dut, plan_parts, truth_record
from rotcal.simulate.spec import SimulationSpec
from rotcal.simulate.timebase_sim import TimebaseDefects, apply_defects
from rotcal.simulate.writers import table_messages, write_metadata

BLOCK_SAMPLES = 1 << 20  # about 100 MB of temporaries in the forward model


def streamable(spec: SimulationSpec, fmt: str) -> bool:
    """Whether ``write_streamed`` can write this dataset (see the module docstring)."""
    return (fmt == "mcap-cdr" and not spec.plan.continuous and not spec.effects and not spec.foreign
            and spec.timebase == TimebaseDefects() and spec.noise == ("", ()))


def _labels(part: dict, index: np.ndarray | slice = slice(None)) -> pl.DataFrame:
    """One plan segment's per-sample labels (those at ``index``), as ``core.schedule`` gives them."""
    t_ns = part["t_ns"][index]
    n = t_ns.size
    return pl.DataFrame({"t_ns": t_ns, "axis": np.repeat(part["axis"], n), "rate_hz": np.full(n, part["rate_hz"]),
                         "angle_deg": part["angle"][index], "plan_segment": np.full(n, part["seg"], np.int32)})


def _table_blocks(part: dict, block: int) -> Iterator[pl.DataFrame]:
    """The table's messages of one plan segment (``writers.table_messages``),
    a block of samples at a time: a rotation's messages in samples a..b are
    those ``table_messages`` finds among the segment's first and last
    samples and samples a-1..b (the sample before tells whether a 0.1 s tick
    starts at a), kept from a to b."""
    n = part["t_ns"].size
    if part["rate_hz"] == 0 or n <= block:
        yield table_messages(_labels(part))
        return
    t_ns = part["t_ns"]
    for a in range(0, n, block):
        b = min(a + block, n)
        index = np.unique(np.r_[0, np.arange(max(a - 1, 0), b), n - 1])
        # from the segment's first message on (half a sample before its first sample, ``table_messages``)
        low = int(t_ns[a]) if a else np.iinfo(np.int64).min
        yield table_messages(_labels(part, index)).filter(pl.col("t_ns").is_between(low, int(t_ns[b - 1])))


def _blocks(parts: Iterator[dict], dut: Dut, effects: Effects, g_local: float, noise_rng: np.random.Generator,
            block: int) -> Iterator[tuple[np.ndarray, list[np.ndarray]]]:
    """The DUT's samples (t_ns, [u, v, w]) a block at a time."""
    t0_s = None
    for part in parts:
        t_ns, angle = part["t_ns"], part["angle"]
        t0_s = t_ns[0] / 1e9 if t0_s is None else t0_s
        for a in range(0, t_ns.size, block):
            t, m = t_ns[a : a + block], min(block, t_ns.size - a)
            motion = Motion(t_s=t / 1e9, axis_idx=np.full(m, axis_index(part["axis"])), rotating=np.full(m, part["rate_hz"] != 0),
                            theta_cmd_deg=angle[a : a + block],
                            t_start_s=np.full(m, t_ns[0] / 1e9), rate_hz=np.full(m, part["rate_hz"]), t0_s=t0_s)
            observed = observe(noise_free_output(motion, dut, effects, g_local), dut, effects, noise_rng)
            yield t, [np.ascontiguousarray(observed[:, r]) for r in range(3)]


def write_streamed(spec: SimulationSpec, seed: int, directory: Path, device_id: str | None = None,
                   block: int = BLOCK_SAMPLES) -> Path:
    """The dataset ``write_dataset(simulate(spec, seed), spec, directory,
    "mcap-cdr")`` writes, generated and written a block at a time
    (``streamable`` specs only)."""
    streams = np.random.SeedSequence(seed).spawn(5)
    dut_rng, plan_rng, effect_rng, noise_rng, logger_rng = (np.random.default_rng(s) for s in streams)
    dut, mount = draw_dut(spec.dut, dut_rng)
    effects, described = build_effects(spec.effects, effect_rng)
    # the table's messages come first in the file: one pass over the plan for them (a segment's
    # messages are in time order and after the last segment's), a second for the samples (the same
    # start angles: a generator from the same seed)
    tables = (table for part in plan_parts(spec.plan, plan_rng) for table in _table_blocks(part, block))
    samples = _blocks(plan_parts(spec.plan, np.random.default_rng(streams[1])), dut, effects, spec.g_local, noise_rng, block)
    directory.mkdir(parents=True, exist_ok=True)
    write_cdr_blocks(samples, tables, directory / "capture.mcap")
    # without defects the logger's realised sizes are zeros whatever the samples: two stamps give them
    logger = apply_defects(pl.DataFrame({"t_ns": [0, 1]}), spec.timebase, logger_rng)[1]
    return write_metadata(spec, truth_record(spec, seed, dut, mount, described, [], logger), directory, "mcap-cdr", device_id)
