"""Segment: split the sample table into segments of one table axis and one
rate, from the labels that came with the data (capture columns,
``[[capture]]`` entries, the MCAP table channel) or hand-placed pose labels.

A static segment is a whole step sequence about one axis (Geist 2017 fits
all steps of an axis at once); its steps are its distinct angles.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.tables import conform


def _same_as_previous(column: pl.Series) -> np.ndarray:
    """Whether each row (from the second) holds the previous row's value,
    two missing values alike (``rle_id``'s runs); categories by their codes."""
    if column.dtype in (pl.Enum, pl.Categorical):
        column = column.to_physical()
    x = column.to_numpy()  # missing values are NaN
    same = x[1:] == x[:-1]
    if column.null_count() or x.dtype.kind == "f":
        same |= np.isnan(x[1:]) & np.isnan(x[:-1])
    return same


def segment_by_labels(samples: pl.DataFrame, dataset: str, angle_source: str = "commanded") -> tuple[pl.DataFrame, pl.DataFrame]:
    """Label runs -> (samples with a ``segment`` column, the segments table).

    A run is a maximal block of consecutive samples of one capture with the
    same axis and rate (or, without them, the same pose label or jig
    reference). Unlabelled samples get a null segment.
    """
    n = samples.height
    present = {c: samples[c].null_count() < n for c in ("axis", "rate_hz", "pose", "gx", "gy", "gz")}
    labelled = samples["axis"].is_not_null().to_numpy() & samples["rate_hz"].is_not_null().to_numpy()
    posed = ~labelled & (samples["pose"].is_not_null().to_numpy() | samples["gx"].is_not_null().to_numpy())
    # 0 static, 1 rotation, 2 pose, -1 outside segments; one byte a sample
    kind = np.where(posed, np.int8(2), np.int8(-1))
    if labelled.any():
        kind[labelled] = samples["rate_hz"].to_numpy()[labelled] != 0
    # Runs by comparing each key column with itself shifted, one column at a
    # time (large captures: one column's temporaries at a time). Absent
    # labels and a single capture's name start no run.
    keys = [c for c, there in present.items() if there]
    keys += ["capture"] if samples.select(pl.col("capture").n_unique()).item() > 1 else []
    start = np.ones(n, bool)  # row 0 starts a run
    if n:
        continuing = np.ones(n - 1, bool)
        for c in keys:
            continuing &= _same_as_previous(samples[c])
        start[1:] = ~continuing
    inside = kind >= 0
    start &= inside
    # int32: the segment column's type (four bytes a sample, not eight)
    segment = np.cumsum(start, dtype=np.int32)
    segment -= 1
    first = np.flatnonzero(start)
    del start
    # a segment ends where the next starts or its rows end (labels absent)
    segment[~inside] = -1
    boundary = np.flatnonzero(segment[1:] != segment[:-1])
    last = boundary[segment[boundary] >= 0]
    last = np.append(last, n - 1) if n and inside[-1] else last
    if inside.all():
        column = pl.Series("segment", segment)
    elif inside.any():
        column = pl.Series("segment", segment).scatter(np.flatnonzero(~inside), None)
    else:  # no labels: no segment (a null column, no list of every row)
        column = pl.repeat(None, n, dtype=pl.Int32, eager=True).alias("segment")
    del segment
    frame = samples.with_columns(column)
    # the samples without an angle and the angle's runs (rle_id), counted between each segment's first and last
    n_missing, n_steps = np.zeros(first.size, np.int64), np.zeros(first.size, np.int64)
    if first.size:
        angle_missing = samples["angle_deg"].is_null().to_numpy()
        missing_before = np.cumsum(angle_missing)
        n_missing = missing_before[last] - missing_before[first] + angle_missing[first]
        del angle_missing, missing_before
        step = np.zeros(n, np.int64)
        np.cumsum(~_same_as_previous(samples["angle_deg"]), out=step[1:])
        n_steps = step[last] - step[first]
    at_first = samples.select("capture", "axis", "rate_hz", "t_ns", "label_source")[first]
    t_ns = samples["t_ns"].to_numpy()
    return frame, segments_frame({
        "segment": pl.Series(np.arange(first.size, dtype=np.int32)),
        "capture": at_first["capture"],
        "kind": pl.Series([("static", "rotation", "pose")[k] for k in kind[first].tolist()], dtype=pl.String),
        "axis": at_first["axis"],
        "rate_hz": at_first["rate_hz"].fill_null(0.0),
        "t_start_ns": at_first["t_ns"],
        "t_end_ns": t_ns[last],
        "n_samples": (last - first + 1).astype(np.int64),
        "n_steps": pl.Series(n_steps + 1),
        "label_source": at_first["label_source"].fill_null("file"),
        "has_angle": n_missing == 0,
    }, dataset, angle_source)


def segments_frame(columns: dict, dataset: str, angle_source: str) -> pl.DataFrame:
    """The ``segments`` table from each segment's labels at its first sample,
    its span, sample count, angle runs (``n_steps``, kept for static
    segments) and whether every sample has an angle (``has_angle``)."""
    return conform(
        pl.DataFrame(columns)
        .with_columns(n_steps=pl.when(pl.col("kind") == "rotation").then(0).otherwise(pl.col("n_steps")))
        .with_columns(
            dataset=pl.lit(dataset),
            n_steps=pl.col("n_steps").cast(pl.Int32),
            angle_source=pl.when(pl.col("has_angle")).then(pl.lit(angle_source)).otherwise(pl.lit("none")),
            # what only inferred or own-phase segments have (rotcal.segment.unlabelled)
            rate_measured_hz=None, rate_u_hz=None, axis_offset_deg=None, chi2_reduced=None, t_phase_ns=None,
        ), "segments")
