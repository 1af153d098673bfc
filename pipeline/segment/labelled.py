"""Segment: split the sample table into segments of one table axis and one
rate, from the labels that came with the data (capture columns,
``[[capture]]`` entries, the MCAP table channel) or hand-placed pose labels.

A static segment is a whole step sequence about one axis (Geist 2017 fits
all steps of an axis at once); its steps are its distinct angles.
"""

from __future__ import annotations

import polars as pl

from rotcal.tables import conform


def segment_by_labels(samples: pl.DataFrame, dataset: str, angle_source: str = "commanded") -> tuple[pl.DataFrame, pl.DataFrame]:
    """Label runs -> (samples with a ``segment`` column, the segments table).

    A run is a maximal block of consecutive samples of one capture with the
    same axis and rate (or, without them, the same pose label or jig
    reference). Unlabelled samples get a null segment.
    """
    labelled = pl.col("axis").is_not_null() & pl.col("rate_hz").is_not_null()
    posed = ~labelled & (pl.col("pose").is_not_null() | pl.col("gx").is_not_null())
    # 0 static, 1 rotation, 2 pose, null outside segments; one byte a sample
    rotating = (labelled & (pl.col("rate_hz") != 0)).cast(pl.Int8)
    kind = pl.when(labelled | posed).then(rotating + 2 * posed.cast(pl.Int8))
    # Runs and segments by cumulative counts, not by sorting or grouping the
    # whole table (large captures: bounded memory). Absent labels and a
    # single capture's name start no run; leaving them out spares
    # materialising them (null_count, and n_unique of a constant, are free).
    keys = [c for c in ("axis", "rate_hz", "pose", "gx", "gy", "gz") if samples[c].null_count() < samples.height]
    keys += ["capture"] if samples.select(pl.col("capture").n_unique()).item() > 1 else []
    frame = samples.with_columns(_kind=kind, _start=pl.lit(False))
    for c in keys:  # one column at a time: one column's temporaries at a time (row 0 starts a run)
        run = pl.col(c).rle_id()
        frame = frame.with_columns(_start=pl.col("_start") | run.ne_missing(run.shift(1)))
    first_of_segment = pl.col("_kind").is_not_null() & pl.col("_start")
    frame = frame.with_columns(
        segment=pl.when(pl.col("_kind").is_not_null()).then(first_of_segment.cum_sum() - 1).cast(pl.Int32)
    ).drop("_start")
    runs = frame.select(pl.col("segment").rle()).unnest("segment").with_columns(first=pl.col("len").cum_sum() - pl.col("len"))
    runs = runs.filter(pl.col("value").is_not_null())
    first, last = runs["first"], runs["first"] + runs["len"] - 1
    angle_null = frame.select(null_before=pl.col("angle_deg").is_null().cum_sum(), step=pl.col("angle_deg").rle_id())
    at_first, at_last = frame.select("capture", "_kind", "axis", "rate_hz", "t_ns", "label_source", "angle_deg")[first], frame["t_ns"][last]
    n_nulls = angle_null["null_before"][last].to_numpy() - angle_null["null_before"][first].to_numpy() + at_first["angle_deg"].is_null().to_numpy()
    return frame.drop("_kind"), segments_frame({
        "segment": runs["value"],
        "capture": at_first["capture"],
        "kind": at_first["_kind"].replace_strict({0: "static", 1: "rotation", 2: "pose"}, return_dtype=pl.String),
        "axis": at_first["axis"],
        "rate_hz": at_first["rate_hz"].fill_null(0.0),
        "t_start_ns": at_first["t_ns"],
        "t_end_ns": at_last,
        "n_samples": runs["len"].cast(pl.Int64),
        "n_steps": pl.Series(angle_null["step"][last].to_numpy() - angle_null["step"][first].to_numpy() + 1),
        "label_source": at_first["label_source"].fill_null("file"),
        "has_angle": n_nulls == 0,
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
