"""Writing a simulated dataset: per-segment CSV files, one unlabelled CSV or
an MCAP capture, with ``dataset.toml`` and the truth (``truth.json``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.errors import ConfigError
from rotcal.ingest.formats.csv.writer import write_samples
from rotcal.simulate.spec import Simulation, SimulationSpec


def segment_files(samples: pl.DataFrame) -> pl.DataFrame:
    """One CSV file name per plan segment: ``NN_axis_static.csv`` or ``NN_axis_RATEhz.csv``."""
    first = samples.filter(pl.col("plan_segment").is_not_null()).group_by("plan_segment", maintain_order=True).agg(pl.col("axis").first(), pl.col("rate_hz").first())
    names = [
        f"{seg:02d}_{axis}_{'static' if rate == 0 else f'{rate:g}hz'}.csv"
        for seg, axis, rate in first.iter_rows()
    ]
    return first.with_columns(file=pl.Series(names))


def _logged(samples: pl.DataFrame) -> tuple[str, ...]:
    """The logged columns beside the outputs: the DUT temperature when simulated."""
    return ("temperature_c",) if "temperature_c" in samples.columns else ()


def write_csv_segments(sim: Simulation, directory: Path) -> list[Path]:
    """The default layout: one CSV per segment with every label column (and
    ``temperature_c`` when an effect drew a temperature history)."""
    files = segment_files(sim.samples)
    columns = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg", *_logged(sim.samples))
    written = []
    for seg, name in files.select("plan_segment", "file").iter_rows():
        part = sim.samples.filter(pl.col("plan_segment") == seg)
        written.append(write_samples(part, directory / name, columns, sim.dut.integer_output))
    return written


def write_csv_single(sim: Simulation, path: Path, columns: tuple[str, ...] = ("t", "u", "v", "w")) -> Path:
    """Everything in one CSV, with only ``columns`` (an unlabelled recording)
    and ``temperature_c`` when an effect drew a temperature history."""
    return write_samples(sim.samples, path, (*columns, *_logged(sim.samples)), sim.dut.integer_output)


def table_messages(samples: pl.DataFrame, period_s: float = 0.1) -> pl.DataFrame:
    """What a table controller publishes: at each segment's and step's start
    and last sample, and every ``period_s`` during rotation. The start's
    message comes half a sample interval before the first sample (the
    table is there before the DUT next samples; at time 0, at it), with the
    commanded angle of that instant: a controller's ticks are not the DUT's
    sampling instants, and a sample whose stamp jitters earlier still
    follows its segment's first message."""
    lead_ns = int(np.median(np.diff(samples["t_ns"].to_numpy()))) // 2 if samples.height > 1 else 0
    frame = samples.with_columns(
        step=pl.struct("plan_segment", pl.when(pl.col("rate_hz") == 0).then(pl.col("angle_deg"))).rle_id()
    )
    first = pl.col("step").is_first_distinct()
    lead = pl.when(first & (pl.col("t_ns") >= lead_ns)).then(lead_ns).otherwise(0)
    edges = frame.filter(first | pl.col("step").is_last_distinct()).with_columns(
        t_ns=pl.col("t_ns") - lead, angle_deg=pl.col("angle_deg") - 360.0 * pl.col("rate_hz") * lead / 1e9)
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
    message, docs/inputs.md) and bias every fit they join; its
    segments are found from the signals, as in ``csv-unlabelled``."""
    from rotcal.ingest.formats.mcap.writer import write_capture

    table = sim.table.clear() if sim.truth["plan"]["continuous"] else sim.table
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
    return write_metadata(spec, sim.truth, directory, fmt, device_id)


def write_metadata(spec: SimulationSpec, truth: dict, directory: Path, fmt: str, device_id: str | None = None) -> Path:
    """A simulated dataset's ``dataset.toml`` and ``truth.json``."""
    full_scale = f"full_scale = {spec.dut.full_scale:g}\n" if spec.dut.full_scale else ""
    # a recording without labels (continuous, or the segments in one file) comes with the plan's nominal
    # rates, as a lab would write them down (a plan of static steps only has none to write: dataset.toml's
    # rates_hz is never empty)
    unlabelled = spec.plan.continuous or fmt == "csv-unlabelled"
    plan = f"\n[plan]\nrates_hz = {list(spec.plan.rates_hz)!r}\n" if unlabelled and spec.plan.rates_hz else ""
    (directory / "dataset.toml").write_text(
        f'[device]\nid = "{device_id or directory.name}"\noutput_unit = "{spec.output_unit}"\n{full_scale}'
        f"\n[site]\ng_local = {spec.g_local!r}\ng_local_uncertainty = {spec.g_local_uncertainty!r}\n{plan}"
    )
    (directory / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    return directory
