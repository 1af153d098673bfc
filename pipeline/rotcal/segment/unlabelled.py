"""Samples without usable labels: their segments inferred from the signals
and their rates measured.

- Unlabelled samples (and static steps labelled without angles) go through
  blind segmentation (``rotcal.segment.blind``): constant rotations, static step
  sequences and single poses, each with ``label_source = "inferred"``.
- Rotation segments without an angle reference (inferred, or labelled with
  axis and rate but no angle) are fitted against their own phase
  (``rotcal.fit.sinefit``); their measured rates are checked against the
  nominal ones and the logger's clock (``rotcal.timebase.rates``).
- Their reduction without an angle reference is ``rotcal.combine.unreferenced``.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import polars as pl

from rotcal.fit.means import pose_table
from rotcal.fit.segments import SegmentFit
from rotcal.fit.sinefit import SineFit, fit_sine
from rotcal.ingest.labels import canonical_rate
from rotcal.model.columns import Outputs, sample_step
from rotcal.model.physics import CHANNELS
from rotcal.segment.blind import BlindConfig, segment_blind
from rotcal.segment.stillness import unused_rows
from rotcal.tables import conform, schema
from rotcal.timebase.rates import PLAN_MATCH, ClockDrift, clock_drift, nominal_rate, rate_classes


@dataclass(frozen=True, eq=False)
class Inference:
    """Samples and segments with the inferred ones added (numbered in time
    order), own-phase fits, the dwells, time-base findings (the clock) and
    what to tell the user."""

    samples: pl.DataFrame
    segments: pl.DataFrame
    fits: tuple[SegmentFit, ...]
    own_phase: frozenset[int]
    dwells: pl.DataFrame
    findings: tuple[dict, ...]
    warnings: tuple[str, ...]
    notes: tuple[str, ...]
    clock_factor: float = 1.0  # what the fitted rates were multiplied by to be on the table's clock (``ClockDrift.factor``)
    route: str = ""  # what the signals showed: rotations, step sequences, chains by hand, dwells (the route's evidence)
    unused: pl.DataFrame | None = None  # the stillness detector's rejections (``still_unused`` rows)


@dataclass(frozen=True, eq=False)
class _Rotation:
    """A rotation segment without an angle reference, before numbering;
    with a ``reason`` its fit only names its rate and it is refused."""

    key: int
    capture: str
    axis: str
    label_source: str
    label_hz: float | None
    fit: SineFit | None
    reason: str | None
    start_ns: int
    end_ns: int
    n_samples: int
    axis_offset_deg: float | None = None
    chi2: float | None = None


@dataclass
class _Found:
    """What blind segmentation adds, gathered over the captures."""

    key: int
    rows: list[dict] = field(default_factory=list)
    rotations: list[_Rotation] = field(default_factory=list)
    dwells: list[pl.DataFrame] = field(default_factory=list)
    unused: list[pl.DataFrame] = field(default_factory=list)
    counts: np.ndarray = field(default_factory=lambda: np.zeros(4, int))


def _segment_row(dataset: str, key: int, capture: str, kind: str, axis: str | None, rate: float, t0: int, t1: int,
                 n: int, steps: int, source: str, **extra) -> dict:
    return {"dataset": dataset, "segment": key, "capture": capture, "kind": kind, "axis": axis, "rate_hz": rate,
            "t_start_ns": t0, "t_end_ns": t1, "n_samples": n, "n_steps": steps, "label_source": source,
            "angle_source": "none", "rate_measured_hz": None, "rate_u_hz": None, "axis_offset_deg": None,
            "chi2_reduced": None, "t_phase_ns": None, **extra}


def _segment_capture(found: _Found, dataset: str, capture: str, t: np.ndarray, y: Outputs, reason: str | None,
                     config: BlindConfig) -> np.ndarray:
    """Blind segmentation of one capture's free samples into ``found``;
    returns each sample's segment key (-1 in transitions)."""
    # stamps too noisy for a fit: keep every steady rotation, to refuse it by name
    blind = segment_blind(t, y, replace(config, max_residual_ratio=np.inf) if reason else config)
    segment = np.full(t.size, -1, np.int32)
    for r in blind.rotations:
        found.rotations.append(_Rotation(found.key, capture, r.axis, "inferred", None, r.fit, reason,
                                         int(t[r.start]), int(t[r.stop - 1]), r.stop - r.start, r.axis_offset_deg,
                                         r.chi2_reduced))
        segment[r.start : r.stop] = found.key
        found.key += 1
    found.counts += [len(blind.rotations), len(blind.sequences), len(blind.dwells), blind.hand_chains]
    if blind.short is not None and blind.short.height:
        found.unused.append(unused_rows(dataset, capture, blind.short, sample_step(t) / 1e9))
    if not len(blind.dwells):
        return segment
    # a one-sample dwell (a file of pose means) has no spread: NaN, as numpy gives it, without its warning
    # (a column at a time: a dwell of millions of samples makes no n x 3 temporaries)
    spread = np.array([[c[s:e].std(ddof=1) for c in y.columns] if e - s > 1 else np.full(y.width, np.nan)
                       for s, e in blind.dwells])
    chi2 = (spread**2 / blind.noise_sd**2).mean(axis=1)
    group = np.full(len(blind.dwells), -1)
    for q in blind.sequences:
        d = blind.dwells[list(q.dwells)]
        group[list(q.dwells)] = found.key
        found.rows.append(_segment_row(dataset, found.key, capture, "static", q.axis, 0.0, int(t[d[0, 0]]),
                                       int(t[d[-1, 1] - 1]), int((d[:, 1] - d[:, 0]).sum()), len(q.dwells), "inferred",
                                       axis_offset_deg=q.axis_offset_deg, chi2_reduced=float(chi2[list(q.dwells)].mean())))
        found.key += 1
    for j in np.flatnonzero(group < 0):
        s, e = blind.dwells[j]
        group[j] = found.key
        found.rows.append(_segment_row(dataset, found.key, capture, "pose", None, 0.0, int(t[s]), int(t[e - 1]),
                                       int(e - s), 1, "inferred", chi2_reduced=float(chi2[j])))
        found.key += 1
    for k, (s, e) in enumerate(blind.dwells):
        segment[s:e] = group[k]
    interval_s = sample_step(t) / 1e9
    found.dwells.append(pose_table(t, y, blind.dwells[:, 0], blind.dwells[:, 1]).with_columns(
        segment=pl.Series(group, dtype=pl.Int32), capture=pl.lit(capture),
        dwell_s=(pl.col("t_end_ns") - pl.col("t_start_ns")).cast(pl.Float64) / 1e9 + interval_s,
        **{f"std_{c}": pl.Series(spread[:, r]) for r, c in enumerate(CHANNELS)},
    ))
    return segment


def _own_phase_fits(rotations: list[_Rotation], dataset: str, plan_rates: tuple[float, ...]
                    ) -> tuple[list[dict], list[dict], list[SegmentFit], ClockDrift]:
    """Rates of the rotations without an angle reference against the nominal
    ones: segment rows of the inferred ones, the fitted columns of the
    labelled ones, every own-phase fit and the logger clock's drift."""
    usable = np.array([r.fit is not None and r.reason is None and r.fit.determined for r in rotations], bool)
    measured = np.array([r.fit.rate_hz if r.fit else np.nan for r in rotations])
    u = np.array([r.fit.rate_u_hz if r.fit else np.nan for r in rotations])
    nominal = np.array([r.label_hz if r.label_hz is not None else
                        (nominal_rate(f, plan_rates) if np.isfinite(f) else None) for r, f in zip(rotations, measured)],
                       dtype=float)
    drift = clock_drift(np.where(usable, measured, np.nan), u, nominal)
    corrected = measured * drift.factor
    u_corrected = np.hypot(u * drift.factor, measured * (drift.u_drift if drift.detected else 0.0))
    rate = np.where(np.isfinite(nominal), nominal, 0.0)
    free = ~np.isfinite(nominal) & np.isfinite(measured)
    rate[free] = rate_classes(corrected[free])
    rows, updates, fits = [], [], []
    for k, r in enumerate(rotations):
        fit = r.fit if usable[k] else None
        measured_cols = {} if fit is None else {
            "rate_measured_hz": float(corrected[k]), "rate_u_hz": float(u_corrected[k]), "t_phase_ns": fit.t_ref_ns}
        if r.label_source == "inferred":
            rows.append(_segment_row(dataset, r.key, r.capture, "rotation", r.axis, float(rate[k]), r.start_ns, r.end_ns,
                                     r.n_samples, 0, "inferred", axis_offset_deg=r.axis_offset_deg, chi2_reduced=r.chi2,
                                     **measured_cols))
        elif measured_cols:
            updates.append({"segment": r.key, **measured_cols})
        fits.append(replace(fit.fit, segment=r.key, rate_fit_hz=float(corrected[k])) if fit is not None else
                    SegmentFit.failed(r.key, r.n_samples, f"time base: {r.reason}" if r.reason else
                                      "its own-phase fit is not determined (too few samples for ten parameters)", float("nan")))
    return rows, updates, fits, drift


def _outputs(samples: pl.DataFrame, rows: np.ndarray | slice) -> np.ndarray:
    """The outputs of some rows, (n, 3)."""
    return np.column_stack([samples[c].to_numpy()[rows] for c in CHANNELS])


def _plan_rates_not_found(plan_rates: tuple[float, ...], segments: pl.DataFrame) -> list[str]:
    """The plan's nominal rates that no rotation segment has: a rotation the
    signals did not show (too short, or not constant) is otherwise lost
    without a word."""
    seen = np.abs(segments.filter(pl.col("kind") == "rotation")["rate_hz"].to_numpy())
    missing = [f for f in sorted({abs(p) for p in plan_rates if p != 0})
               if not np.any(np.abs(seen / f - 1.0) <= PLAN_MATCH)]
    return [f"[plan] rates_hz: no constant rotation at {', '.join(f'{f:g}' for f in missing)} Hz was found"] if missing else []


def infer_segments(samples: pl.DataFrame, segments: pl.DataFrame, dataset: str, plan_rates: tuple[float, ...] = (),
                   unrepairable: dict[str, str] | None = None, config: BlindConfig = BlindConfig()) -> Inference:
    """Add the segments that labels do not give; fit rotations without an
    angle reference against their own phase."""
    unrepairable = unrepairable or {}
    static_no_angle = segments.filter((pl.col("kind") == "static") & (pl.col("angle_source") == "none"))["segment"]
    kept = segments.filter(~pl.col("segment").is_in(static_no_angle.implode()))
    seg_col = samples["segment"].fill_null(-1).to_numpy().copy()
    free = (seg_col < 0) | np.isin(seg_col, static_no_angle.to_numpy())
    seg_col[free] = -1
    t_all = samples["t_ns"].to_numpy()
    found = _Found(int(segments["segment"].to_numpy().max()) + 1 if segments.height else 0)
    # the outputs are gathered only for the samples a step needs (no copy of a whole labelled recording)
    captures = samples["capture"].filter(pl.Series(free)).unique(maintain_order=True).to_list()
    for capture in captures:
        idx = np.flatnonzero(free & (samples["capture"] == capture).to_numpy())
        # one run of rows (a whole capture): views, not copies
        part: np.ndarray | slice = slice(int(idx[0]), int(idx[-1]) + 1) if idx.size and idx[-1] - idx[0] + 1 == idx.size else idx
        if idx.size >= 10:
            del idx
            # the outputs as columns (views of a whole capture's): as np.column_stack would give them, without the copy
            seg_col[part] = _segment_capture(found, dataset, capture, t_all[part], Outputs.of_frame(samples, part),
                                             unrepairable.get(capture), config)
    hand = (f", {found.counts[3]} chain(s) of dwells about one axis without a table's steps (directions off one great "
            "circle, or unequal steps: poses turned by hand)") if found.counts[3] else ""
    route = (f"{found.counts[0]} constant rotations, {found.counts[1]} static step sequences{hand}, {found.counts[2]} dwells "
             "in all") if captures else ""
    notes = [f"segments inferred from the signals of {len(captures)} capture(s): {route}"] if captures else []
    for row in kept.filter((pl.col("kind") == "rotation") & (pl.col("angle_source") == "none")).iter_rows(named=True):
        on = seg_col == row["segment"]
        reason = unrepairable.get(row["capture"])
        fit = None if reason else fit_sine(t_all[on], _outputs(samples, np.flatnonzero(on)), abs(row["rate_hz"]))
        found.rotations.append(_Rotation(row["segment"], row["capture"], row["axis"], row["label_source"],
                                         row["rate_hz"], fit, reason, row["t_start_ns"], row["t_end_ns"], int(on.sum())))
    rows, updates, fits, drift = _own_phase_fits(found.rotations, dataset, plan_rates)
    warnings = drift.warnings()
    if updates:
        kept = kept.update(pl.DataFrame(updates, schema_overrides={"segment": pl.Int32}), on="segment")
    new = pl.DataFrame(found.rows + rows, schema=schema("segments").polars_schema) if found.rows or rows else schema("segments").empty()
    every = pl.concat([conform(kept, "segments"), new]).with_columns(rate_hz=canonical_rate(pl.col("rate_hz")))
    warnings += _plan_rates_not_found(plan_rates, every)
    # number every segment in time order
    order = every.sort("t_start_ns", "segment")["segment"].to_numpy()
    lookup = np.full(int(order.max(initial=-1)) + 2, -1, np.int32)  # the last entry serves -1: no segment
    lookup[order] = np.arange(order.size)
    renumber = {int(old): int(new) for new, old in enumerate(order)}
    if not np.array_equal(order, np.arange(order.size)):  # else numbered in time order already
        every = every.with_columns(segment=pl.col("segment").replace_strict(renumber, return_dtype=pl.Int32)).sort("segment")
    if free.any() or not np.array_equal(order, np.arange(order.size)):  # else every sample keeps its segment
        seg_col = lookup[seg_col]
        samples = samples.with_columns(segment=pl.Series(np.ma.masked_array(seg_col, seg_col < 0), dtype=pl.Int32))
    numbered = tuple(replace(f, segment=int(lookup[f.segment])) for f in fits)
    dwells = schema("dwells").empty() if not found.dwells else conform(
        pl.concat(found.dwells).sort("t_start_ns").with_columns(
            dataset=pl.lit(dataset), dwell=pl.int_range(pl.len(), dtype=pl.Int32),
            segment=pl.col("segment").replace_strict(renumber, return_dtype=pl.Int32),
            g_magnitude=pl.lit(None, pl.Float64)), "dwells")
    return Inference(samples, conform(every, "segments"), numbered, frozenset(f.segment for f in numbered), dwells,
                     (drift.finding(dataset),) if found.rotations else (), tuple(warnings), tuple(notes), drift.factor, route,
                     pl.concat(found.unused) if found.unused else None)

