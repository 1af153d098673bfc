"""Pose summaries: a static calibration given as one row per pose (docs/inputs.md,
"Pose summaries") instead of the samples, as many authors publish a
six-position test: the pose (a label or the jig reference ``gx, gy, gz``)
and per channel the mean, the sample standard deviation and the sample count
(optionally the channels' sample correlations); or the means alone, as
ellipsoid-fit tools such as Magneto take them, whose scatter the static
reduction then takes from its fit's residuals.

They are the statistics the static reduction takes from a pose's samples
(``combine.poses``: the mean and the covariance of the mean, std^2 / n per
channel); ``combine.poses.summary_poses`` turns them into the same pose
table, so both reach the same fit.
"""

from __future__ import annotations

from pathlib import Path

import polars as pl

from rotcal.errors import InputError
from rotcal.ingest.labels import POSES, REFERENCES, check_references, check_values
from rotcal.model.physics import CHANNELS

MEANS = tuple(f"{c}_mean" for c in CHANNELS)
STDS = tuple(f"{c}_std" for c in CHANNELS)
COUNTS = tuple(f"{c}_n" for c in CHANNELS)
# optional: the sample correlation of two channels' noise (the pairs of a covariance's off-diagonal)
CORRELATIONS = ("corr_uv", "corr_vw", "corr_wu")
# every column a summary file may hold (besides [format] pose_column); ``n``: one count for all channels
SUMMARY_COLUMNS = (*REFERENCES, "temperature_c", *MEANS, *STDS, *COUNTS, "n", *CORRELATIONS)
SUMMARY_SCHEMA = {"pose": pl.String, **dict.fromkeys((*REFERENCES, "temperature_c", *MEANS, *STDS), pl.Float64),
                  **dict.fromkeys(COUNTS, pl.Int64), **dict.fromkeys(CORRELATIONS, pl.Float64)}


def scatterless(columns: list[str]) -> bool:
    """Pose means alone (Magneto's input, one row per pose): no standard deviation or count column."""
    return not any(c in columns for c in (*STDS, *COUNTS, "n"))


def _missing(columns: list[str]) -> list[str]:
    if scatterless(columns):
        return [c for c in MEANS if c not in columns]
    missing = [c for c in (*MEANS, *STDS) if c not in columns]
    if "n" not in columns:
        missing += [c for c in COUNTS if c not in columns]
    return missing


def pose_summaries(frame: pl.DataFrame, path: Path) -> pl.DataFrame:
    """One summary file's rows, checked, in the columns of ``SUMMARY_SCHEMA``
    (``n`` spread to ``u_n, v_n, w_n``; an unknown label is null)."""
    missing = _missing(frame.columns)
    if missing:
        raise InputError(f"pose summaries need the columns {', '.join(map(repr, missing))} "
                         f"(columns found: {', '.join(sorted(frame.columns))})", path=path)
    means_only = scatterless(frame.columns)
    if means_only:  # the scatter is then the fit's residuals' (combine.static): no noise known, zero covariance
        frame = frame.with_columns(*(pl.lit(0.0).alias(c) for c in STDS), *(pl.lit(1, pl.Int64).alias(c) for c in COUNTS))
    if "n" in frame.columns:
        frame = frame.with_columns(pl.col("n").alias(c) for c in COUNTS if c not in frame.columns).drop("n")
    check_values(frame, path, required=(*MEANS, *STDS, *COUNTS))
    check_references(frame, path)
    for name in () if means_only else COUNTS:
        counts = frame[name]
        bad = ((counts < 2) | (counts != counts.round())).arg_true()
        if len(bad):
            raise InputError(f"column {name!r}, row {int(bad[0]) + 1}: {counts[int(bad[0])]:g} is not a sample count "
                             "of 2 or more (the standard deviation needs two samples)", path=path)
    for name in (c for c in CORRELATIONS if c in frame.columns):
        bad = (frame[name].abs() > 1).arg_true()
        if len(bad):
            raise InputError(f"column {name!r}, row {int(bad[0]) + 1}: {frame[name][int(bad[0])]:g} is not a correlation "
                             "(-1 to 1)", path=path)
    for name in () if means_only else STDS:
        bad = (frame[name] <= 0).arg_true()
        if len(bad):
            raise InputError(f"column {name!r}, row {int(bad[0]) + 1}: a standard deviation of {frame[name][int(bad[0])]:g}; "
                             "it must be above 0", path=path)
    label = pl.col("pose").str.strip_chars() if "pose" in frame.columns else pl.lit(None, pl.String)
    frame = frame.with_columns(pose=pl.when(label.is_in(POSES)).then(label).otherwise(None))
    frame = frame.with_columns(pl.lit(None, t).alias(c) for c, t in SUMMARY_SCHEMA.items() if c not in frame.columns)
    placed = pl.col("pose").is_not_null() | pl.all_horizontal(pl.col(c).is_not_null() for c in REFERENCES)
    unplaced = frame.select(~placed).to_series().arg_true()
    if 0 < len(unplaced) < frame.height:  # none placed: poses of unknown orientation, fitted as still intervals are
        raise InputError(f"row {int(unplaced[0]) + 1}: neither a pose label (x_p, x_a, ..., z_a in [format] pose_column) "
                         "nor a reference gx, gy, gz, where other rows have one: say how every pose rested, or none",
                         path=path)
    return frame.select(pl.col(c).cast(t) for c, t in SUMMARY_SCHEMA.items())
