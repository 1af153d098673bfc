"""Time base: check each capture's stamps against a regular sampling grid,
measure every defect, and repair what can be repaired honestly.

A digital sensor samples on its own clock, so its samples sit on a grid
``t_k = a + T k``; a logger stamps them, drops some, writes some twice and
adds noise to the stamps. rotcal fits the grid (the period ``T`` common to the
capture, one offset ``a`` per logging run) by least squares to the stamps,
with every sample's slot ``k`` from rounding; two iterations make the slots
exact (a slot is misread only if a stamp is off by half a period).

What it finds, per capture:

- duplicated records (same stamp, same values): dropped;
- repeated stamps (distinct samples sharing a stamp): placed in the free
  neighbouring slots when the sampling is regular, else dropped;
- missing samples (empty slots) and gaps (runs of ``gap_min_slots`` or more):
  reported; the fits use each sample's own time, so nothing needs repair;
- logging pauses: a gap after which the grid's phase changes (the logger
  stopped and restarted); each run keeps its own offset;
- stamp jitter: the white part of the stamps' residuals from the grid. When
  it is detectable and the residuals are white and bounded (every sample
  within half a period of its slot), the sampling is regular and only the
  stamps are noisy: the stamps are replaced by the fitted grid;
- irregular sampling: residuals that wander smoothly (the stamps follow a
  clock that is corrected in steps, or the sampling itself is irregular):
  the stamps are kept.

Jitter too large to place the samples on the grid cannot be repaired: the
capture is marked, and rotation segments in it are refused downstream.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from pipeline.errors import InputError
from pipeline.physics import CHANNELS
from pipeline.tables import conform, schema


@dataclass(frozen=True)
class TimebaseConfig:
    jitter_floor: float = 1e-3     # stamp noise below this fraction of the period is not a defect
    gap_min_slots: int = 5         # this many consecutive missing samples or more: a gap (lost packets)
    white_max_lag1: float = 0.5    # residual lag-1 autocorrelation above this: wander, not jitter


@dataclass(frozen=True)
class Finding:
    """One check of one capture (a row of ``timebase.parquet``)."""

    check: str
    detected: bool
    value: float
    std_uncertainty: float | None
    unit: str
    action: str
    evidence: str


@dataclass(frozen=True, eq=False)
class CaptureTimebase:
    """The outcome for one capture: which rows stay, their (repaired) stamps,
    the fitted period, and the findings. ``unrepairable`` says why the time
    base cannot carry a rotation fit (None when it can)."""

    keep: np.ndarray
    t_ns: np.ndarray
    interval_s: float
    findings: tuple[Finding, ...]
    unrepairable: str | None = None
    warnings: tuple[str, ...] = field(default=())


def _grid_fit(s: np.ndarray, k: np.ndarray, run: np.ndarray) -> tuple[float, np.ndarray]:
    """Least squares ``s = a_run + T k``: the common period and each run's offset."""
    n_runs = int(run.max()) + 1
    count = np.bincount(run, minlength=n_runs)
    k_mean = np.bincount(run, k, n_runs) / count
    s_mean = np.bincount(run, s, n_runs) / count
    dk = k - k_mean[run]
    den = float(dk @ dk)
    period = float(dk @ (s - s_mean[run]) / den) if den > 0 else float(np.median(np.diff(s)))
    return period, s_mean - period * k_mean


def _robust_sd(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if x.size else 0.0


def _place_collisions(slot: np.ndarray, run: np.ndarray) -> np.ndarray:
    """New slots for samples that share one. The group of m samples claiming
    slot k fills k .. k+m-1 when exactly those slots are free (the previous
    sample sits at k-1 and the next at k+m), or k-m+1 .. k when exactly
    those are; only then do the empty slots say where they belong. Otherwise
    the samples get -1 (cannot be placed)."""
    key = run.astype(np.int64) * (1 << 40) + slot
    start = np.r_[True, key[1:] != key[:-1]]
    group = np.cumsum(start) - 1
    first = np.flatnonzero(start)
    size = np.diff(np.r_[first, key.size])
    pos = np.arange(key.size) - first[group]
    prev_key = np.r_[np.iinfo(np.int64).min, key[first[1:] - 1]]
    next_key = np.r_[key[first[:-1] + size[:-1]], np.iinfo(np.int64).max]
    up = (next_key == key[first] + size) & (prev_key == key[first] - 1)
    down = (prev_key == key[first] - size) & (next_key == key[first] + 1)
    new = np.where(up[group], slot + pos, np.where(down[group], slot - size[group] + 1 + pos, -1))
    return np.where(size[group] == 1, slot, new)


def _slots(s: np.ndarray, d: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Every stamp's slot on the grid and its logging run: slots counted
    from the intervals, runs split at every gap and joined again where the
    next run's line continues this one's (lost packets: the phase holds);
    then every slot re-read from the fitted lines. Returns the slots, the
    runs, the period and each run's offset."""
    # equal stamps share a slot (a repeated stamp); any advance is at least one slot
    steps = np.where(d > 0, np.maximum(np.rint(d / period), 1.0), 0.0)
    run = np.r_[0, np.cumsum(steps >= 2)]
    k = np.r_[0.0, np.cumsum(steps)]
    distinct = np.r_[1.0, d > 0]
    for _ in range(3):
        period, offset = _grid_fit(s, k, run)
        resid = s - offset[run] - period * k
        jitter = _robust_sd(np.diff(resid)[np.diff(run) == 0]) / np.sqrt(2.0)
        u_offset = np.maximum(jitter, 1.0) / np.sqrt(np.maximum(np.bincount(run, distinct), 1.0))
        slip = (offset[1:] - offset[:-1]) / period
        whole = np.rint(slip)
        tolerance = np.minimum(4 * np.hypot(u_offset[1:], u_offset[:-1]) + 1e-4 * period, period / 2)
        hold = np.abs(slip - whole) * period < tolerance
        k = k + np.r_[0.0, np.cumsum(np.where(hold, whole, 0.0))][run]
        run = np.r_[0, np.cumsum(~hold)][run]
        period, offset = _grid_fit(s, k, run)
        k = np.rint((s - offset[run]) / period)
    period, offset = _grid_fit(s, k, run)
    return k, run, period, offset


def check_capture(t_ns: np.ndarray, y: np.ndarray, capture: str, config: TimebaseConfig = TimebaseConfig()) -> CaptureTimebase:
    """Check and repair one capture's stamps (sorted, as ingest leaves them)."""
    n = t_ns.size
    if n < 3:
        return CaptureTimebase(np.ones(n, bool), t_ns.copy(), float("nan"), ())
    same = np.r_[False, (np.diff(t_ns) == 0) & np.all(np.diff(y, axis=0) == 0, axis=1)]
    keep = ~same
    s = t_ns[keep].astype(np.float64)
    d = np.diff(s)
    if s.size < 2 or np.count_nonzero(d > 0) < d.size / 2:
        raise InputError(f"capture {capture}: the time stamps do not advance (most consecutive stamps are equal)",
                         hint="give [format] sample_rate_hz and no time column")
    k, run, period, offset = _slots(s, d, float(np.median(d[d > 0])))
    resid = s - offset[run] - period * k
    within = np.diff(run) == 0
    jitter = _robust_sd(np.diff(resid)[within]) / np.sqrt(2.0)
    r0, r1 = resid[:-1][within], resid[1:][within]
    lag1 = float(np.corrcoef(r0, r1)[0, 1]) if r0.size > 2 and np.std(r0) > 0 and np.std(r1) > 0 else 0.0
    spread = float(np.std(resid))
    floor = config.jitter_floor * period
    jittery = jitter > floor
    # white scatter about the grid: the sampling is regular and only the stamps are noisy
    white = spread <= floor or lag1 < config.white_max_lag1
    placeable = jitter < period / 9  # half a period is 4.5 standard deviations
    regular = white and placeable
    repeated = np.r_[False, d == 0]

    findings, warnings = [], []
    unit_period = period / 1e9
    u_period = float(np.sqrt(np.sum(resid**2) / max(n - 2, 1) / np.sum((k - k.mean()) ** 2))) / 1e9
    findings.append(Finding("sample_interval", False, unit_period, u_period, "s", "none",
                            f"{s.size} samples on a grid of {unit_period * 1e3:.6g} ms"))
    n_dup = int(same.sum())
    findings.append(Finding("duplicated_samples", n_dup > 0, float(n_dup), None, "1", "dropped" if n_dup else "none",
                            f"{n_dup} records repeat the previous record exactly (stamp and values)"))
    if n_dup:
        warnings.append(f"{capture}: {n_dup} duplicated records dropped")

    if regular:
        placed = _place_collisions(k.astype(np.int64), run)
        unplaceable = placed < 0
        repeated |= np.r_[False, (np.diff(k) == 0) & within]
    else:
        placed, unplaceable = k.astype(np.int64), repeated
    n_rep = int(repeated.sum())
    action = ("none" if not n_rep else "placed on the regular time base" if regular
              else "dropped: the sampling is not regular, their times are unknown")
    findings.append(Finding("repeated_stamps", n_rep > 0, float(n_rep), None, "1", action,
                            f"{n_rep} samples share their stamp with another sample; "
                            f"{int(unplaceable.sum())} could not be placed"))
    if n_rep:
        warnings.append(f"{capture}: {n_rep} samples with repeated stamps ({action})")

    good = ~unplaceable
    if regular:
        holes = np.concatenate([np.diff(np.unique(placed[good & (run == r)])) - 1 for r in np.unique(run[good])])
        n_missing = int(holes.sum()) - int(unplaceable.sum())  # samples that could not be placed fill some holes
    else:
        holes = np.where(within & (d > 0), np.maximum(np.rint(d / period), 1.0) - 1, 0.0)
        n_missing = int(holes.sum())
    gap_lengths = holes[holes >= config.gap_min_slots]
    total = n_missing + int(good.sum())
    findings.append(Finding("missing_samples", n_missing > 0, float(n_missing), None, "1",
                            "none: each sample keeps its own time",
                            f"{n_missing} of {total} grid slots have no sample ({100 * n_missing / max(total, 1):.3g} %)"))
    longest = float(gap_lengths.max()) * unit_period if gap_lengths.size else 0.0
    findings.append(Finding("gaps", gap_lengths.size > 0, longest, None, "s", "none: each sample keeps its own time",
                            f"{gap_lengths.size} runs of {config.gap_min_slots} or more missing samples, "
                            f"longest {longest:.3g} s, {float(gap_lengths.sum()) * unit_period:.3g} s in all"))
    if n_missing:
        warnings.append(f"{capture}: {n_missing} samples missing ({100 * n_missing / max(total, 1):.3g} %), "
                        f"{gap_lengths.size} gaps, longest {longest:.3g} s")
    n_pauses = int(run.max())
    findings.append(Finding("logging_pauses", False, float(n_pauses), None, "1", "none: each run keeps its own phase",
                            f"{n_pauses} gaps after which the sampling grid's phase changes (the logger "
                            f"stopped and restarted: not a defect)"))

    unrepairable = None
    refit = jittery and regular
    if refit:
        action = "refit: stamps replaced by the regular time base"
        warnings.append(f"{capture}: timestamp jitter {jitter / 1e6:.3g} ms (sd), samples placed on the regular "
                        f"{unit_period * 1e3:.6g} ms time base")
    elif jittery and white:
        action = "none: too large to place samples on the grid"
        unrepairable = (f"timestamp jitter of {jitter / 1e6:.3g} ms (sd) is too large against the "
                        f"{unit_period * 1e3:.6g} ms sample interval to place the samples on a regular time base")
        warnings.append(f"{capture}: {unrepairable}")
    else:
        action = "none"
    findings.append(Finding("timestamp_jitter", jittery, jitter / 1e9, jitter / 1e9 / np.sqrt(2 * max(s.size - 1, 1)), "s", action,
                            f"white scatter of the stamps about the grid {jitter / 1e6:.3g} ms (sd), "
                            f"residual lag-1 autocorrelation {lag1:.2f}"))
    wander = not white
    findings.append(Finding("irregular_sampling", wander, spread / 1e9, None, "s", "kept the stamps" if wander else "none",
                            f"stamps deviate from a regular grid by {spread / 1e6:.3g} ms (sd), "
                            f"{float(np.abs(resid).max()) / 1e6:.3g} ms at most, residual lag-1 autocorrelation {lag1:.2f}"))

    grid = offset[run] + period * placed
    t_out = t_ns[keep].copy()
    if refit:
        t_out = np.rint(grid).astype(np.int64)
    elif regular:
        moved = (placed != k) & good
        t_out[moved] = np.rint(grid[moved]).astype(np.int64)
    keep[np.flatnonzero(keep)[unplaceable]] = False
    return CaptureTimebase(keep, t_out[good], unit_period, tuple(findings), unrepairable, tuple(warnings))


@dataclass(frozen=True, eq=False)
class TimebaseResult:
    """Repaired samples, the findings table, warnings, and the captures whose
    time base cannot carry a rotation fit (capture -> reason)."""

    samples: pl.DataFrame
    findings: pl.DataFrame
    warnings: tuple[str, ...]
    unrepairable: dict[str, str]


def repair_timebase(samples: pl.DataFrame, dataset: str, config: TimebaseConfig = TimebaseConfig()) -> TimebaseResult:
    """Check every capture of the canonical sample table and repair it."""
    parts, rows, warnings, bad = [], [], [], {}
    for (capture,), part in samples.group_by("capture", maintain_order=True):
        tb = check_capture(part["t_ns"].to_numpy(), part.select(CHANNELS).to_numpy(), capture, config)
        parts.append(part.filter(pl.Series(tb.keep)).with_columns(t_ns=pl.Series(tb.t_ns, dtype=pl.Int64)))
        rows += [{"dataset": dataset, "capture": capture, **f.__dict__} for f in tb.findings]
        warnings += tb.warnings
        if tb.unrepairable:
            bad[capture] = tb.unrepairable
    repaired = pl.concat(parts).sort("t_ns", maintain_order=True) if parts else samples
    return TimebaseResult(repaired, findings_frame(rows), tuple(warnings), bad)


def findings_frame(rows: list[dict]) -> pl.DataFrame:
    """The ``timebase`` table."""
    if not rows:
        return schema("timebase").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("timebase").polars_schema, strict=False), "timebase")
