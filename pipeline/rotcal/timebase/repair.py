"""The time base of a dataset: every capture checked against its sampling
grid and repaired (``repair_timebase``, with ``check.check_capture``), the
samples put back in time order; once the segments are known, the gaps
between them called logging pauses (``classify_gaps``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import polars as pl

from rotcal.ingest.labels import time_ordered
from rotcal.model.physics import CHANNELS
from rotcal.timebase.check import Gaps, TimebaseConfig, check_capture, findings_frame
from rotcal.timebase.grid import kept


@dataclass(frozen=True, eq=False)
class TimebaseResult:
    """Repaired samples, the findings table, warnings, and the captures whose
    time base cannot carry a rotation fit (capture -> reason)."""

    samples: pl.DataFrame
    findings: pl.DataFrame
    warnings: tuple[str, ...]
    unrepairable: dict[str, str]
    gaps: tuple[Gaps, ...] = ()


def repair_timebase(samples: pl.DataFrame, dataset: str, config: TimebaseConfig = TimebaseConfig()) -> TimebaseResult:
    """Check every capture of the canonical sample table and repair it. The
    table is copied only as far as something changes: rows dropped only if
    some are, stamps replaced only if some moved, rows sorted only if out of
    order."""
    rows, warnings, bad = list[dict](), list[str](), dict[str, str]()  # findings, warnings, captures that cannot carry a fit
    captures = samples["capture"].unique(maintain_order=True).to_list()
    keep, stamps, gaps = np.ones(samples.height, bool), None, []
    t_all, y_all = samples["t_ns"].to_numpy(), [samples[c].to_numpy() for c in CHANNELS]
    for capture, where in zip(captures, capture_rows(samples["capture"], len(captures))):
        t = t_all if where is None else t_all[where]
        tb = check_capture(t, [y if where is None else y[where] for y in y_all], capture, config)
        keep[slice(None) if where is None else where] = tb.keep
        if not np.array_equal(tb.t_ns, kept(t, tb.keep)):
            stamps = t_all.copy() if stamps is None else stamps
            stamps[np.flatnonzero(keep) if where is None else np.arange(t_all.size)[where][tb.keep]] = tb.t_ns
        rows += [{"dataset": dataset, "capture": capture, **f.__dict__} for f in tb.findings]
        warnings += tb.warnings
        gaps += [tb.gaps] if tb.gaps else []
        if tb.unrepairable:
            bad[capture] = tb.unrepairable
    repaired = samples if stamps is None else samples.with_columns(t_ns=pl.Series(stamps, dtype=pl.Int64))
    repaired = repaired if keep.all() else repaired.filter(pl.Series(keep))
    return TimebaseResult(_time_ordered(repaired, captures), findings_frame(rows), tuple(warnings), bad, tuple(gaps))


def capture_rows(capture: pl.Series, n_captures: int) -> list[slice | np.ndarray | None]:
    """Each capture's rows, in order of first appearance: None (the one capture), slices where each
    is one run of rows (as ingest reads them, file after file), else row numbers."""
    if n_captures == 1:
        return [None]
    code = capture.to_physical().to_numpy()
    edges = np.concatenate(([0], np.flatnonzero(code[1:] != code[:-1]) + 1, [code.size]))
    return ([slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])] if edges.size - 1 == n_captures
            else [np.flatnonzero(code == c) for c in capture.unique(maintain_order=True).to_physical().to_numpy()])


def classify_gaps(result: TimebaseResult, samples: pl.DataFrame, segments: pl.DataFrame) -> TimebaseResult:
    """The time base once the segments are known: a gap is missing samples
    only inside a segment (the samples on both sides in one segment, and in
    a static sequence on one step: the same ``angle_deg``); a gap between
    segments, or between the steps of a sequence, is a logging pause (the
    logger rested while the table moved), whatever the grid's phase. Lone
    missing samples stay missing wherever they are. ``samples`` carry the
    ``segment`` column; the result is ``result`` itself when no gap moves."""
    static = segments.filter(pl.col("kind") == "static")["segment"].to_numpy()
    rows, warnings = result.findings.to_dicts(), list(result.warnings)
    changed = False
    for gaps in result.gaps:
        if not gaps.length.size:
            continue
        mine = samples.filter(pl.col("capture") == gaps.capture)
        t = mine["t_ns"].to_numpy()
        segment = mine["segment"].fill_null(-1).to_numpy()
        step = mine["angle_deg"].fill_null(np.nan).to_numpy()
        on_step = np.isin(segment, static)
        after = np.clip(np.searchsorted(t, gaps.middle_ns), 1, max(t.size - 1, 1))
        before = after - 1
        same_step = ~on_step[before] | (step[before] == step[after]) | (np.isnan(step[before]) & np.isnan(step[after]))
        between = ~((segment[before] == segment[after]) & (segment[before] >= 0) & same_step)
        if not between.any():
            continue
        changed = True
        old_warning = gaps.findings()[1]
        new_findings, new_warning = gaps.findings(between)
        renewed = {f.check: f for f in new_findings}
        rows = [{**r, **renewed[r["check"]].__dict__} if r["capture"] == gaps.capture and r["check"] in renewed else r
                for r in rows]
        warnings = [w for w in warnings if w != old_warning] if new_warning is None else \
            [new_warning if w == old_warning else w for w in warnings]
    if not changed:
        return result
    return replace(result, findings=findings_frame(rows), warnings=tuple(warnings))


def _time_ordered(samples: pl.DataFrame, captures: list[str]) -> pl.DataFrame:
    """Sorted by time, stably, and at equal stamps capture by capture in the
    order of ``captures``; a table already in that order is only marked so."""
    if len(captures) < 2:
        return time_ordered(samples)
    t = samples["t_ns"].to_numpy()
    if np.all(t[1:] > t[:-1]):  # no equal stamps: the captures' ranks need not be known
        return samples.with_columns(pl.col("t_ns").set_sorted())
    rank = pl.col("capture").replace_strict(captures, range(len(captures)), return_dtype=pl.UInt32)
    r = samples.select(rank)["capture"].to_numpy()
    if np.all((t[1:] > t[:-1]) | ((t[1:] == t[:-1]) & (r[1:] >= r[:-1]))):
        return samples.with_columns(pl.col("t_ns").set_sorted())
    return samples.with_columns(_rank=rank).sort("t_ns", "_rank", maintain_order=True).drop("_rank")
