"""Segment: split the sample table into segments of one table axis and one
rate, from the labels that came with the data (capture columns,
``[[capture]]`` entries, the MCAP table channel) or hand-placed pose labels.

A static segment is a whole step sequence about one axis (Geist 2017 fits
all steps of an axis at once); its steps are its distinct angles.
"""

from __future__ import annotations

import polars as pl

from pipeline.tables import conform


def segment_by_labels(samples: pl.DataFrame, dataset: str, angle_source: str = "commanded") -> tuple[pl.DataFrame, pl.DataFrame]:
    """Label runs -> (samples with a ``segment`` column, the segments table).

    A run is a maximal block of consecutive samples of one capture with the
    same axis and rate (or, without them, the same pose label or jig
    reference). Unlabelled samples get a null segment.
    """
    labelled = pl.col("axis").is_not_null() & pl.col("rate_hz").is_not_null()
    posed = ~labelled & (pl.col("pose").is_not_null() | pl.col("gx").is_not_null())
    frame = samples.with_columns(
        _run=pl.struct("capture", "axis", "rate_hz", "pose", "gx", "gy", "gz").rle_id(),
        _kind=pl.when(labelled)
        .then(pl.when(pl.col("rate_hz") == 0).then(pl.lit("static")).otherwise(pl.lit("rotation")))
        .when(posed)
        .then(pl.lit("pose"))
        .otherwise(None),
    )
    in_segment = pl.col("_kind").is_not_null()
    frame = frame.with_columns(
        segment=(pl.when(in_segment).then(pl.col("_run")).rank("dense") - 1).cast(pl.Int32)
    )
    segments = (
        frame.filter(in_segment)
        .group_by("segment", maintain_order=True)
        .agg(
            capture=pl.col("capture").first(),
            kind=pl.col("_kind").first(),
            axis=pl.col("axis").first(),
            rate_hz=pl.col("rate_hz").first().fill_null(0.0),
            t_start_ns=pl.col("t_ns").first(),
            t_end_ns=pl.col("t_ns").last(),
            n_samples=pl.len().cast(pl.Int64),
            n_steps=pl.when(pl.col("_kind").first() == "rotation").then(0).otherwise(pl.col("angle_deg").rle_id().max() + 1),
            label_source=pl.col("label_source").first().fill_null("file"),
            has_angle=pl.col("angle_deg").is_not_null().all(),
        )
        .with_columns(
            dataset=pl.lit(dataset),
            n_steps=pl.col("n_steps").cast(pl.Int32),
            angle_source=pl.when(pl.col("has_angle")).then(pl.lit(angle_source)).otherwise(pl.lit("none")),
            # what only inferred or own-phase segments have (pipeline.unlabelled)
            rate_measured_hz=None, rate_u_hz=None, axis_offset_deg=None, chi2_reduced=None, t_phase_ns=None,
        )
    )
    return frame.drop("_run", "_kind"), conform(segments, "segments")
