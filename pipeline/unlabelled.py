"""Samples without usable labels: their segments inferred from the signals,
their rates measured and checked against the plan (the logger's clock), and
their reduction without an angle reference.

- Unlabelled samples (and static steps labelled without angles) go through
  blind segmentation (``pipeline.blind``): constant rotations, static step
  sequences and single poses, each with ``label_source = "inferred"``.
- Rotation segments without an angle reference (inferred, or labelled with
  axis and rate but no angle) are fitted against their own phase
  (``pipeline.sinefit``); the rate is measured.
- The measured rates against the nominal ones (a segment's label, or the
  nearest of ``[plan] rates_hz``): a logger clock that runs fast by d makes
  every rate look slow by the same factor 1 / (1 + d). The weighted mean of
  the segments' factors is the drift; when it is significant and the
  segments agree on it, the measured rates are corrected. A table whose rate
  is off by the same factor looks the same: the two cannot be told apart
  without an independent reference.
- Reduction: per rate, the rotation segments go to ``pipeline.phasefree``
  (segments with a table angle enter with their phase fixed); the dwells to
  ``pipeline.multiposition.orientation_free`` (rate 0) when no labelled
  static sequence gives the static result.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import polars as pl

from pipeline.blind import BlindConfig, noise_sd_of, segment_blind
from pipeline.combine import CombineFailure, IntrinsicResult, segment_coefficients
from pipeline.fit import SegmentFit
from pipeline.ingest.labels import canonical_rate
from pipeline.multiposition import OrientationFreeFit, orientation_free, pose_table
from pipeline.phasefree import PhaseSegment, solve_phase_free
from pipeline.physics import CHANNELS
from pipeline.sinefit import SineFit, fit_sine
from pipeline.tables import conform, schema

PLAN_MATCH = 0.02      # a measured rate within this fraction of a nominal one is that rate
CLASS_WIDTH = 0.01     # measured rates within this fraction of each other form one rate (no nominal rates)
DRIFT_CONSISTENCY = 1e-3  # chi-square p-value below which the segments do not share one clock factor


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


@dataclass
class _Rotation:
    key: int
    capture: str
    axis: str
    label_source: str
    nominal_hz: float | None
    fit: SineFit | None
    reason: str | None
    start_ns: int
    end_ns: int
    n_samples: int
    axis_offset_deg: float | None = None
    chi2: float | None = None


def _segment_row(dataset: str, key: int, capture: str, kind: str, axis: str | None, rate: float, t0: int, t1: int,
                 n: int, steps: int, source: str, **extra) -> dict:
    return {"dataset": dataset, "segment": key, "capture": capture, "kind": kind, "axis": axis, "rate_hz": rate,
            "t_start_ns": t0, "t_end_ns": t1, "n_samples": n, "n_steps": steps, "label_source": source,
            "angle_source": "none", "rate_measured_hz": None, "rate_u_hz": None, "axis_offset_deg": None,
            "chi2_reduced": None, "t_phase_ns": None, **extra}


def _nominal(rate_hz: float, plan_rates: tuple[float, ...]) -> float | None:
    if not plan_rates:
        return None
    plan = np.asarray(plan_rates)
    k = int(np.argmin(np.abs(np.log(np.abs(plan) / rate_hz))))
    return float(plan[k]) if abs(abs(plan[k]) / rate_hz - 1.0) <= PLAN_MATCH else None


def clock_drift(rotations: list[_Rotation]) -> tuple[float, float, float, int]:
    """Weighted mean of d_k = nominal / measured - 1 over the segments with a
    nominal rate: (d, its standard uncertainty scaled by the Birge ratio when
    the segments scatter more than their uncertainties say, chi-square, number)."""
    use = [r for r in rotations if r.fit is not None and r.nominal_hz]
    if not use:
        return float("nan"), float("nan"), float("nan"), 0
    f = np.array([r.fit.rate_hz for r in use])
    u = np.array([r.fit.rate_u_hz for r in use])
    nominal = np.abs([r.nominal_hz for r in use])
    d = nominal / f - 1.0
    u_d = np.maximum(nominal * u / f**2, 1e-300)
    w = 1.0 / u_d**2
    mean = float(np.sum(w * d) / np.sum(w))
    chi2 = float(np.sum(w * (d - mean) ** 2))
    birge = np.sqrt(chi2 / (len(use) - 1)) if len(use) > 1 else 1.0
    return mean, float(max(birge, 1.0) / np.sqrt(np.sum(w))), chi2, len(use)


def _drift_finding(dataset: str, rotations: list[_Rotation]) -> tuple[dict, float, list[str]]:
    """The clock-drift row of the time-base table, the factor to apply to the
    measured rates, and warnings."""
    from scipy.stats import chi2 as chi2_dist

    d, u, chi2, n = clock_drift(rotations)
    row = {"dataset": dataset, "capture": "", "check": "clock_drift", "unit": "ppm"}
    if n == 0:
        return {**row, "detected": False, "value": float("nan"), "std_uncertainty": None, "action": "none",
                "evidence": "no nominal rates (segment labels or [plan] rates_hz): the logger clock cannot be "
                            "compared with the table"}, 1.0, []
    consistent = n < 2 or chi2_dist.sf(chi2, n - 1) >= DRIFT_CONSISTENCY
    detected = consistent and abs(d) > 3 * u
    evidence = (f"{n} rotation segments measure rates {d * 1e6:.4g} ppm slow against the nominal ones "
                f"(chi-square {chi2:.3g} on {max(n - 1, 0)} degrees of freedom): the logger clock runs fast "
                f"by that much against the table (or the table slow)")
    if not consistent:
        return ({**row, "detected": False, "value": d * 1e6, "std_uncertainty": u * 1e6, "action": "none",
                 "evidence": evidence + "; the segments disagree, so this is not one clock factor"}, 1.0,
                [f"the measured rates are not off from the nominal ones by one common factor "
                 f"(chi-square {chi2:.3g} on {n - 1} degrees of freedom): rates kept as measured"])
    action = "corrected: measured rates multiplied by 1 + drift" if detected else "none"
    warnings = [f"logger clock drift {d * 1e6:.4g} +- {u * 1e6:.2g} ppm against the table: rates corrected"] if detected else []
    return ({**row, "detected": detected, "value": d * 1e6, "std_uncertainty": u * 1e6, "action": action,
             "evidence": evidence}, (1.0 + d) if detected else 1.0, warnings)


def _rate_classes(rates: np.ndarray) -> np.ndarray:
    """Class means of measured rates (no nominal rates): sorted rates within
    CLASS_WIDTH of their neighbour are one rate."""
    order = np.argsort(rates)
    r = rates[order]
    cls = np.r_[0, np.cumsum(np.diff(r) > CLASS_WIDTH * r[1:])] if r.size else np.zeros(0, int)
    means = np.bincount(cls, r) / np.bincount(cls) if r.size else np.zeros(0)
    out = np.empty_like(rates)
    out[order] = means[cls]
    return out


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
    y_all = samples.select(CHANNELS).to_numpy().astype(float)
    capture_col = samples["capture"].to_numpy()
    key = int(segments["segment"].max() + 1) if segments.height else 0
    rows, dwell_parts, rotations, notes, warnings = [], [], [], [], []
    found = np.zeros(3, int)
    for capture in dict.fromkeys(capture_col[free]):
        idx = np.flatnonzero(free & (capture_col == capture))
        if idx.size < 10:
            continue
        t, y = t_all[idx], y_all[idx]
        # stamps too noisy for a fit: keep every steady rotation, to refuse it by name
        blind = segment_blind(t, y, replace(config, max_residual_ratio=np.inf) if capture in unrepairable else config)
        for r in blind.rotations:
            reason = unrepairable.get(capture)
            rotations.append(_Rotation(key, capture, r.axis, "inferred", None, None if reason else r.fit, reason,
                                       int(t[r.start]), int(t[r.stop - 1]), r.stop - r.start, r.axis_offset_deg,
                                       r.chi2_reduced))
            seg_col[idx[r.start : r.stop]] = key
            key += 1
        group = np.full(len(blind.dwells), -1)
        for q in blind.sequences:
            group[list(q.dwells)] = key
            d = blind.dwells[list(q.dwells)]
            rows.append(_segment_row(dataset, key, capture, "static", q.axis, 0.0, int(t[d[0, 0]]), int(t[d[-1, 1] - 1]),
                                     int((d[:, 1] - d[:, 0]).sum()), len(q.dwells), "inferred",
                                     axis_offset_deg=q.axis_offset_deg))
            key += 1
        for j in np.flatnonzero(group < 0):
            s, e = blind.dwells[j]
            group[j] = key
            rows.append(_segment_row(dataset, key, capture, "pose", None, 0.0, int(t[s]), int(t[e - 1]), int(e - s), 1,
                                     "inferred"))
            key += 1
        if len(blind.dwells):
            poses = pose_table(t, y, blind.dwells[:, 0], blind.dwells[:, 1])
            spread = np.array([y[s:e].std(axis=0, ddof=1) for s, e in blind.dwells])
            dwell_parts.append(poses.with_columns(
                segment=pl.Series(group, dtype=pl.Int32), capture=pl.lit(capture),
                dwell_s=(pl.col("t_end_ns") - pl.col("t_start_ns")).cast(pl.Float64) / 1e9 + float(np.median(np.diff(t))) / 1e9,
                **{f"std_{c}": pl.Series(spread[:, r]) for r, c in enumerate(CHANNELS)},
            ))
            for j, (s, e) in enumerate(blind.dwells):
                seg_col[idx[s:e]] = group[j]
            chi2 = (spread**2 / blind.noise_sd**2).mean(axis=1)
            for row in rows:
                if row["capture"] == capture and row["kind"] in ("static", "pose") and row["chi2_reduced"] is None:
                    row["chi2_reduced"] = float(chi2[group == row["segment"]].mean())
        found += [len(blind.rotations), len(blind.sequences), len(blind.dwells)]

    if free.any():
        notes.append(f"segments inferred from the signals of {len(set(capture_col[free]))} capture(s): "
                     f"{found[0]} constant rotations, {found[1]} static step sequences, {found[2]} dwells in all")
    for row in kept.filter((pl.col("kind") == "rotation") & (pl.col("angle_source") == "none")).iter_rows(named=True):
        on = seg_col == row["segment"]
        t, y = t_all[on], y_all[on]
        reason = unrepairable.get(row["capture"])
        fit = None if reason else fit_sine(t, y, abs(row["rate_hz"]))
        rotations.append(_Rotation(row["segment"], row["capture"], row["axis"], row["label_source"], row["rate_hz"],
                                   fit, reason, row["t_start_ns"], row["t_end_ns"], int(on.sum())))

    for r in rotations:
        if r.nominal_hz is None and r.fit is not None:
            r.nominal_hz = _nominal(r.fit.rate_hz, plan_rates)
    finding, factor, drift_warnings = _drift_finding(dataset, rotations)
    warnings += drift_warnings
    measured = np.array([r.fit.rate_hz * factor if r.fit else np.nan for r in rotations])
    classes = _rate_classes(measured[np.isfinite(measured)])
    class_of = dict(zip(np.flatnonzero(np.isfinite(measured)), classes))
    drift_u = (finding.get("std_uncertainty") or 0.0) * 1e-6 if factor != 1.0 else 0.0
    fits, own_labelled = [], []
    for k, r in enumerate(rotations):
        f = r.fit
        fitted = {} if f is None else {"rate_measured_hz": float(measured[k]), "t_phase_ns": f.t_ref_ns,
                                       "rate_u_hz": float(np.hypot(f.rate_u_hz * factor, f.rate_hz * drift_u))}
        if r.label_source == "inferred":
            rate = r.nominal_hz if r.nominal_hz is not None else float(class_of.get(k, 0.0))
            rows.append(_segment_row(dataset, r.key, r.capture, "rotation", r.axis, rate, r.start_ns, r.end_ns,
                                     r.n_samples, 0, "inferred", axis_offset_deg=r.axis_offset_deg,
                                     chi2_reduced=r.chi2, **fitted))
        elif fitted:
            own_labelled.append({"segment": r.key, **fitted})
        fits.append(SegmentFit.failed(r.key, r.n_samples, f"time base: {r.reason}", float("nan")) if f is None else
                    replace(f.fit, segment=r.key, rate_fit_hz=float(measured[k])))
    if own_labelled:
        kept = kept.update(pl.DataFrame(own_labelled, schema_overrides={"segment": pl.Int32}), on="segment")
    new = pl.DataFrame(rows, schema=schema("segments").polars_schema) if rows else schema("segments").empty()
    every = pl.concat([conform(kept, "segments"), new]).with_columns(rate_hz=canonical_rate(pl.col("rate_hz")))
    # number every segment in time order
    order = every.sort("t_start_ns", "segment")["segment"].to_list()
    renumber = {old: i for i, old in enumerate(order)}
    every = every.with_columns(segment=pl.col("segment").replace_strict(renumber, return_dtype=pl.Int32)).sort("segment")
    lookup = np.full(max(order, default=-1) + 2, -1)
    lookup[np.array(order, dtype=int)] = np.arange(len(order))
    seg_col = np.where(seg_col >= 0, lookup[np.maximum(seg_col, 0)], -1)
    samples = samples.with_columns(segment=pl.Series(np.where(seg_col >= 0, seg_col, None).tolist(), dtype=pl.Int32))
    fits = tuple(replace(f, segment=int(lookup[f.segment])) for f in fits)
    dwells = _dwells_frame(dwell_parts, dataset, lookup)
    return Inference(samples, conform(every, "segments"), fits, frozenset(f.segment for f in fits), dwells,
                     (finding,) if rotations else (), tuple(warnings), tuple(notes))


def _dwells_frame(parts: list[pl.DataFrame], dataset: str, lookup: np.ndarray) -> pl.DataFrame:
    if not parts:
        return schema("dwells").empty()
    frame = pl.concat(parts).sort("t_start_ns").with_columns(
        dataset=pl.lit(dataset), dwell=pl.int_range(pl.len(), dtype=pl.Int32),
        segment=pl.col("segment").replace_strict({int(k): int(v) for k, v in enumerate(lookup) if v >= 0},
                                                 return_dtype=pl.Int32),
        g_magnitude=pl.lit(None, pl.Float64),
    )
    return conform(frame, "dwells")


def reduce_unreferenced(fits: pl.DataFrame, own_phase: frozenset[int], dwells: pl.DataFrame, need_static: bool,
                        g_local: float, g_uncertainty: float
                        ) -> tuple[list[IntrinsicResult | CombineFailure], pl.DataFrame, dict[float, float]]:
    """Results of the rates that have rotation segments without an angle
    reference, and of rate 0 from the dwells when ``need_static``; the
    dwells with their |a| after calibration; each phase-free rate's
    chi-square per degree of freedom (the consistency of the components
    measured twice)."""
    results, consistency = [], {}
    rotating = fits.filter((pl.col("kind") == "rotation") & (pl.col("status") == "ok"))
    own_rates = sorted(set(rotating.filter(pl.col("segment").is_in(list(own_phase)))["rate_hz"].to_list()))
    for rate in own_rates:
        segs = segment_coefficients(rotating.filter(pl.col("rate_hz") == rate))
        solved = solve_phase_free(rate, [PhaseSegment(s.segment, s.axis, s.coef, s.cov, s.segment not in own_phase)
                                         for s in segs], g_local, g_uncertainty)
        if isinstance(solved, CombineFailure):
            results.append(solved)
        else:
            results.append(solved.result)
            consistency[rate] = solved.chi2 / max(solved.dof, 1)
    if need_static and dwells.height:
        poses = dwells.rename({"dwell": "pose"})
        fit = orientation_free(poses, g_local, g_uncertainty)
        if isinstance(fit, OrientationFreeFit):
            results.append(fit.result)
            dwells = dwells.with_columns(g_magnitude=pl.Series(fit.magnitude))
        else:
            results.append(CombineFailure(0.0, f"static dwells: {fit.reason}"))
    return results, dwells, consistency
