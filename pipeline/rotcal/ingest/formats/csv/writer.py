"""A sample table written as a CSV capture (docs/inputs.md, "CSV captures"):
``t`` in seconds, then the columns asked for, as the reader reads them back."""

from __future__ import annotations

from pathlib import Path

import polars as pl

from rotcal.model.conventions import CHANNELS

LABELLED = ("t", "u", "v", "w", "axis", "rate_hz", "angle_deg")


def csv_columns(samples: pl.DataFrame, columns: tuple[str, ...], integer: bool = False) -> pl.DataFrame:
    """``columns`` of a sample table (``t_ns`` as ``t`` in seconds), the channels as integers where ``integer``."""
    out = samples.with_columns(t=pl.col("t_ns") / 1e9)
    if integer:
        out = out.with_columns(pl.col(c).cast(pl.Int64) for c in CHANNELS)
    return out.select(columns)


def write_samples(samples: pl.DataFrame, path: Path, columns: tuple[str, ...] | None = None,
                  integer: bool = False) -> Path:
    """The registry's writer (``ingest.formats``): ``samples`` as one CSV
    capture with ``columns`` (default: t, the channels and the labels it has)."""
    columns = columns or tuple(c for c in LABELLED if c == "t" or c in samples.columns)
    csv_columns(samples, columns, integer).write_csv(path)
    return path
