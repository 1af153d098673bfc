"""Checks of the unlabelled path against simulated truth, shared by the
tests and ``scripts/measure_unlabelled.py``: one seeded continuous
recording of the default test plan, reduced blind (t, u, v, w only) and, for
comparison, with its labels."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.model.physics import INTRINSIC
from rotcal.run import run_dataset
from rotcal.simulate import Plan, SimulationSpec, simulate, write_dataset

DEFECTS = "drop_fraction=0.01,duplicate_fraction=0.005,repeat_stamp_fraction=0.005,jitter_s=0.005,clock_drift_ppm=200"


@dataclass(frozen=True)
class Checked:
    """Figures of one seed: worst boundary error (s), axis errors, worst
    relative rate error, segments found / expected, extra segments that are
    not rests, the largest |blind - labelled| / u per rotation rate (empty
    without a labelled run), every (value - truth) / u per rate, and the
    time-base findings next to the truth."""

    seed: int
    boundary_s: float
    axis_errors: int
    rate_rel: float
    found: int
    expected: int
    spurious: int
    vs_labelled: dict
    z_truth: dict
    timebase: dict

    @property
    def vs_truth(self) -> dict:
        return {rate: float(np.abs(z).max()) for rate, z in self.z_truth.items()}


def _continuous(defects: str | None) -> SimulationSpec:
    spec = SimulationSpec(plan=Plan(continuous=True))
    return spec.with_timebase(defects) if defects else spec


def _truth_segments(truth: dict) -> list[dict]:
    """The plan's segments: every rotation and every static step sequence."""
    out = []
    for p in truth["timeline"]:
        if p["kind"] == "rotation":
            out.append(dict(p))
        elif p["kind"] == "step":
            if out and out[-1]["kind"] == "static" and out[-1]["plan_segment"] == p["plan_segment"]:
                out[-1]["t_end_s"] = p["t_end_s"]
                out[-1]["steps"] += 1
            else:
                out.append({**p, "kind": "static", "steps": 1})
    return out


def _intrinsic(out: Path) -> pl.DataFrame:
    return pl.read_parquet(out / "intrinsic.parquet")


def check_seed(seed: int, work: Path, defects: str | None = None, labelled: bool = True) -> Checked:
    """Simulate, run blind (and labelled), and compare."""
    spec = _continuous(defects)
    sim = simulate(spec, seed)
    truth = sim.truth
    blind_dir = write_dataset(sim, spec, work / f"blind{seed}", "csv-unlabelled")
    if defects is None:
        # without [plan] rates_hz: the rates come from the signals alone
        toml = blind_dir / "dataset.toml"
        toml.write_text(toml.read_text().split("\n[plan]")[0])
    blind_out = work / f"blind{seed}_out"
    run_dataset(blind_dir, blind_out)
    segs = pl.read_parquet(blind_out / "segments.parquet")
    dt = truth["plan"]["dt_s"]
    worst, axis_err, rate_rel, found = 0.0, 0, 0.0, 0
    used = set()
    for p in _truth_segments(truth):
        kind = p["kind"]
        cand = segs.filter(pl.col("kind") == kind).with_columns(
            overlap=pl.min_horizontal(pl.col("t_end_ns") / 1e9, pl.lit(p["t_end_s"]))
            - pl.max_horizontal(pl.col("t_start_ns") / 1e9, pl.lit(p["t_start_s"])))
        best = cand.sort("overlap", descending=True).head(1)
        if best.height == 0 or best["overlap"][0] <= 0:
            continue
        row = best.row(0, named=True)
        used.add(row["segment"])
        found += 1
        err = max(abs(row["t_start_ns"] / 1e9 - p["t_start_s"]), abs(row["t_end_ns"] / 1e9 + dt - p["t_end_s"]))
        worst = max(worst, err)
        axis_err += row["axis"] != p["axis"]
        if kind == "rotation":
            rate_rel = max(rate_rel, abs(row["rate_measured_hz"] / p["rate_hz"] - 1.0))
    rests = [(p["t_start_s"], p["t_end_s"]) for p in truth["timeline"] if p["kind"] in ("pause", "step")]
    spurious = 0
    for row in segs.filter(~pl.col("segment").is_in(list(used))).iter_rows(named=True):
        mid = (row["t_start_ns"] + row["t_end_ns"]) / 2e9
        spurious += not (row["kind"] == "pose" and any(a <= mid <= b for a, b in rests))

    values = {p: truth["intrinsic"][p] for p in INTRINSIC}
    blind = _intrinsic(blind_out)
    z_truth = {rate: part.select((pl.col("value") - pl.col("parameter").replace_strict(values))
                                 / pl.col("std_uncertainty")).to_series().to_list()
               for (rate,), part in blind.group_by("rate_hz")}
    vs_labelled = {}
    if labelled:
        lab_dir = write_dataset(sim, spec, work / f"lab{seed}", "csv")
        lab_out = work / f"lab{seed}_out"
        run_dataset(lab_dir, lab_out)
        lab = _intrinsic(lab_out).filter(pl.col("rate_hz") > 0)
        nominal = np.array(sorted(lab["rate_hz"].unique()))
        b = blind.filter(pl.col("rate_hz") > 0).with_columns(
            rate_hz=pl.col("rate_hz").map_elements(lambda r: float(nominal[np.argmin(np.abs(nominal - r))]), return_dtype=pl.Float64))
        joined = b.join(lab, on=["rate_hz", "parameter"], suffix="_lab")
        vs_labelled = {rate: float(part.select(((pl.col("value") - pl.col("value_lab")) / pl.col("std_uncertainty_lab")).abs().max()).item())
                       for (rate,), part in joined.group_by("rate_hz")}
    tb = pl.read_parquet(blind_out / "timebase.parquet")
    reported = {c: (d, v) for c, d, v in tb.select("check", "detected", "value").iter_rows()}
    return Checked(seed, worst, axis_err, rate_rel, found, len(_truth_segments(truth)), spurious,
                   vs_labelled, z_truth, {"reported": reported, "truth": truth["timebase"]})
