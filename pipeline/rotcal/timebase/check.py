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
  stopped and restarted); each run keeps its own offset. Once the segments
  are known (``classify_gaps``), a gap that falls between segments is a
  pause too, whatever its phase: the logger rested while the table moved,
  and no sample a fit uses is missing;
- stamp jitter: the white part of the stamps' residuals from the grid. When
  it is detectable and the residuals are white and bounded (every sample
  within half a period of its slot), the sampling is regular and only the
  stamps are noisy: the stamps are replaced by the fitted grid;
- irregular sampling: residuals that wander smoothly (the stamps follow a
  clock that is corrected in steps, or the sampling itself is irregular):
  the stamps are kept.

Jitter too large to place the samples on the grid cannot be repaired: the
capture is marked, and rotation segments in it are refused downstream.

This module checks one capture (``check_capture``) and words its findings;
``repair`` applies it to every capture of a dataset.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from rotcal.errors import InputError
from rotcal.tables import conform, schema
from rotcal.timebase.grid import grid_residuals, grid_slots, intervals, kept, lag1_within, median, place_collisions


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
class Gaps:
    """A capture's empty grid slots: ``missing`` in all (lone samples and
    gaps) of ``slots``; each gap (``min_slots`` or more in a row) by the
    time of its middle and its length in slots; and the pauses after which
    the grid's phase changes."""

    capture: str
    missing: int
    slots: int
    period_s: float
    middle_ns: np.ndarray
    length: np.ndarray
    phase_pauses: int
    min_slots: int

    def findings(self, between: np.ndarray | None = None) -> tuple[tuple[Finding, ...], str | None]:
        """The ``missing_samples``, ``gaps`` and ``logging_pauses`` findings and the warning, the gaps
        marked ``between`` segments counted as pauses (not as missing samples; nor more samples than slots)."""
        between = np.zeros(self.length.size, bool) if between is None else between
        inside = self.length[~between]
        paused = int(self.length[between].sum())
        missing, total = self.missing - paused, self.slots - paused
        share = f"{100 * missing / max(total, 1):.3g} %"
        longest = float(inside.max()) * self.period_s if inside.size else 0.0
        n_pauses = self.phase_pauses + int(between.sum())
        over = f"{-missing} more samples than the {total} grid slots: the stamps jitter by half a period or more"
        restarted = (f"{self.phase_pauses} gaps after which the sampling grid's phase changes (the logger "
                     f"stopped and restarted: not a defect)")
        found = (
            Finding("missing_samples", missing > 0, float(max(missing, 0)), None, "1", "none: each sample keeps its own time",
                    f"{missing} of {total} grid slots have no sample ({share})" if missing >= 0 else over),
            Finding("gaps", inside.size > 0, longest, None, "s", "none: each sample keeps its own time",
                    f"{inside.size} runs of {self.min_slots} or more missing samples, "
                    f"longest {longest:.3g} s, {float(inside.sum()) * self.period_s:.3g} s in all"),
            Finding("logging_pauses", False, float(n_pauses), None, "1", "none: each run keeps its own phase",
                    restarted if not between.any() else
                    f"{restarted}; {int(between.sum())} gaps between segments, {paused * self.period_s:.3g} s "
                    f"in all (the logger rested while the table moved: not a defect)"),
        )
        warning = (f"{self.capture}: {missing} samples missing ({share}), {inside.size} gaps, longest {longest:.3g} s"
                   if missing > 0 else f"{self.capture}: {over}" if missing < 0 else None)
        return found, warning


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
    gaps: Gaps | None = None


@dataclass(frozen=True)
class GridStats:
    """What a capture's time-base findings are worded from: the records and
    those kept (duplicates dropped), the fitted period (ns) and its
    uncertainty (s), the white jitter, the residuals' lag-1
    autocorrelation, sd and largest magnitude (ns)."""

    n: int
    n_kept: int
    period: float
    u_period: float
    jitter: float
    lag1: float
    spread: float
    largest: float

    def regularity(self, config: TimebaseConfig) -> tuple[bool, bool, bool]:
        """Whether the jitter is detectable, the scatter white, and the sampling regular."""
        floor = config.jitter_floor * self.period
        # white scatter about the grid: the sampling is regular and only the stamps are noisy
        white = self.spread <= floor or self.lag1 < config.white_max_lag1
        placeable = self.jitter < self.period / 9  # half a period is 4.5 standard deviations
        return self.jitter > floor, white, white and placeable


def grid_findings(stats: GridStats, n_rep: int, n_unplaceable: int, gaps: Gaps, capture: str,
                  config: TimebaseConfig) -> tuple[tuple[Finding, ...], tuple[str, ...], str | None, bool]:
    """A capture's findings and warnings, why its time base cannot carry a
    rotation fit (None if it can), and whether its stamps are replaced by
    the fitted grid; ``n_rep`` samples with repeated stamps, ``n_unplaceable``
    of them not placed."""
    jittery, white, regular = stats.regularity(config)
    jitter, lag1 = stats.jitter, stats.lag1
    findings, warnings = [], []
    unit_period = stats.period / 1e9
    findings.append(Finding("sample_interval", False, unit_period, stats.u_period, "s", "none",
                            f"{stats.n_kept} samples on a grid of {unit_period * 1e3:.6g} ms"))
    n_dup = stats.n - stats.n_kept
    findings.append(Finding("duplicated_samples", n_dup > 0, float(n_dup), None, "1", "dropped" if n_dup else "none",
                            f"{n_dup} records repeat the previous record exactly (stamp and values)"))
    if n_dup:
        warnings.append(f"{capture}: {n_dup} duplicated records dropped")
    action = ("none" if not n_rep else "placed on the regular time base" if regular
              else "dropped: the sampling is not regular, their times are unknown")
    findings.append(Finding("repeated_stamps", n_rep > 0, float(n_rep), None, "1", action,
                            f"{n_rep} samples share their stamp with another sample; {n_unplaceable} could not be placed"))
    if n_rep:
        warnings.append(f"{capture}: {n_rep} samples with repeated stamps ({action})")
    gap_findings, gap_warning = gaps.findings()
    findings += gap_findings
    warnings += [gap_warning] if gap_warning else []

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
    findings.append(Finding("timestamp_jitter", jittery, jitter / 1e9, jitter / 1e9 / np.sqrt(2 * max(stats.n_kept - 1, 1)),
                            "s", action, f"white scatter of the stamps about the grid {jitter / 1e6:.3g} ms (sd), "
                            f"residual lag-1 autocorrelation {lag1:.2f}"))
    wander = not white
    findings.append(Finding("irregular_sampling", wander, stats.spread / 1e9, None, "s", "kept the stamps" if wander else "none",
                            f"stamps deviate from a regular grid by {stats.spread / 1e6:.3g} ms (sd), "
                            f"{stats.largest / 1e6:.3g} ms at most, residual lag-1 autocorrelation {lag1:.2f}"))
    return tuple(findings), tuple(warnings), unrepairable, refit


# Captures run to millions of samples: the sample-length arrays are built in
# place where the arithmetic allows and dropped as soon as they are done with,
# with every value computed exactly as the straightforward expression would.
# The stamps ``s`` stay int64; numpy converts them to float64 inside each
# operation exactly as ``astype`` would.


def check_capture(t_ns: np.ndarray, channels, capture: str, config: TimebaseConfig = TimebaseConfig()) -> CaptureTimebase:
    """Check and repair one capture's stamps (sorted, as ingest leaves them);
    ``channels`` are its outputs, one array per channel. Where nothing
    changes the stamps returned are ``t_ns`` itself."""
    n = t_ns.size
    if n < 3:
        return CaptureTimebase(np.ones(n, bool), t_ns.copy(), float("nan"), ())
    tie = np.flatnonzero(t_ns[1:] == t_ns[:-1])  # a record can repeat only where its stamp does
    keep = np.ones(n, bool)
    if tie.size:
        keep[tie + 1] = ~np.all([(c[tie + 1] - c[tie]) == 0 for c in channels], axis=0)
    s = kept(t_ns, keep)
    d = intervals(s)
    if s.size < 2 or np.count_nonzero(d > 0) < d.size / 2:
        raise InputError(f"capture {capture}: the time stamps do not advance (most consecutive stamps are equal)",
                         hint="give [format] sample_rate_hz and no time column")
    first_period = median(d[d > 0])
    del d
    k, run, period, offset, jitter = grid_slots(s, first_period)
    repeated = np.concatenate(([False], intervals(s) == 0))
    resid = grid_residuals(s, k, run, period, offset)
    within = run[1:] == run[:-1]
    lag1 = lag1_within(resid, within)
    spread, largest = float(np.std(resid)), float(max(resid.max(), -resid.min()))
    np.square(resid, out=resid)
    ss_resid = np.sum(resid)
    del resid
    dk = k - (np.bincount(run, k) / np.bincount(run))[run]  # about each run's mean: each run has its own offset
    np.square(dk, out=dk)
    u_period = float(np.sqrt(ss_resid / max(s.size - 2 - int(run.max()), 1) / np.sum(dk))) / 1e9  # n - 1 - runs dof
    del dk
    slot = k.astype(np.int64)
    del k
    stats = GridStats(n, s.size, period, u_period, jitter, lag1, spread, largest)
    jittery, white, regular = stats.regularity(config)
    if regular:
        placed = place_collisions(slot, run)
        unplaceable = placed < 0
        repeated[1:] |= (slot[1:] == slot[:-1]) & within
    else:
        placed, unplaceable = slot, repeated

    good = ~unplaceable
    if regular:
        # the empty slots between the distinct placed slots of each run
        p, r = kept(placed, good), kept(run, good)
        if not np.all((r[1:] > r[:-1]) | ((r[1:] == r[:-1]) & (p[1:] >= p[:-1]))):
            order = np.lexsort((p, r))
            p, r = p[order], r[order]
        step = np.diff(p)
        counted = (r[1:] == r[:-1]) & (step != 0)
        # samples that could not be placed fill some holes
        n_missing = int(np.sum(step, where=counted)) - int(counted.sum()) - int(unplaceable.sum())
        at_gap = counted & (step > config.gap_min_slots)
        gap_lengths = step[at_gap] - 1
        gap_middle = offset[r[1:][at_gap]] + period * (p[1:][at_gap] + p[:-1][at_gap]) / 2
        del p, r, step, counted
    else:
        d = intervals(s)
        holes = np.where(within & (d > 0), np.maximum(np.rint(d / period), 1.0) - 1, 0.0)
        n_missing = int(holes.sum())
        at_gap = holes >= config.gap_min_slots
        gap_lengths = holes[at_gap]
        gap_middle = (s[1:][at_gap] + s[:-1][at_gap]) / 2
    gaps = Gaps(capture, n_missing, n_missing + int(good.sum()), period / 1e9, gap_middle, gap_lengths, int(run.max()),
                config.gap_min_slots)
    findings, warnings, unrepairable, refit = grid_findings(stats, int(repeated.sum()), int(unplaceable.sum()), gaps,
                                                            capture, config)

    t_out = s
    if refit:
        grid = offset[run]  # the regular time base, offset[run] + period * placed
        grid += period * placed
        t_out = np.rint(grid, out=grid).astype(np.int64)
    elif regular:
        moved = np.flatnonzero((placed != slot) & good)
        if moved.size:
            t_out = s.copy()
            t_out[moved] = np.rint(offset[run[moved]] + period * placed[moved]).astype(np.int64)
    keep[np.flatnonzero(keep)[unplaceable]] = False
    return CaptureTimebase(keep, kept(t_out, good), period / 1e9, findings, unrepairable, warnings, gaps)


def findings_frame(rows: list[dict]) -> pl.DataFrame:
    """The ``timebase`` table."""
    if not rows:
        return schema("timebase").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("timebase").polars_schema, strict=False), "timebase")
