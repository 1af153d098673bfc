"""Turn one capture's raw columns into the canonical sample columns: time in
int64 nanoseconds, validated labels, ``[[capture]]`` labels filled in.

Every source (CSV, MCAP with CDR or JSON) ends here, so every source obeys
the same rules.
"""

from __future__ import annotations

import math
from pathlib import Path

import polars as pl

from rotcal.errors import InputError
from rotcal.ingest.meta import CaptureSpec
from rotcal.model.physics import AXES
from rotcal.tables import schema

POSES = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
OPTIONAL_FLOATS = ("rate_hz", "angle_deg", "temperature_c", "gx", "gy", "gz")
# The largest magnitude a sample value may have: far beyond any sensor's output,
# rate or table angle, and small enough that sums of squares of millions of
# them stay finite in float64 (u = 1e308 overflowed to NaN parameters).
MAX_ABS_VALUE = 1e15
# Times in seconds become int64 nanoseconds, which end at 2^63 ns = 9.22e9 s:
# 9e9 s keeps Unix-epoch times (1.7e9 s now) for two more centuries.
MAX_ABS_TIME_S = 9e9
REFERENCES = ("gx", "gy", "gz")
# a jig reference is a unit vector in g; 5 % allows a tilted jig's rounded components
REFERENCE_TOLERANCE = 0.05


def time_ordered(frame: pl.DataFrame) -> pl.DataFrame:
    """Sorted by ``t_ns``, stably; a frame already in order is only marked so
    (a sort would copy every column)."""
    if frame["t_ns"].is_sorted():
        return frame.with_columns(pl.col("t_ns").set_sorted())
    return frame.sort("t_ns", maintain_order=True)


def nanoseconds(seconds: pl.Expr) -> pl.Expr:
    """Times in seconds as int64 nanoseconds, by one rounding (half away from zero)."""
    return (seconds * 1e9).round().cast(pl.Int64)


def canonical_rate(rate: pl.Expr) -> pl.Expr:
    """Rates to the nearest nanohertz, so one plan rate compares equal whatever
    path (CSV text, a joint velocity in rad/s) it arrived by."""
    return (rate * 1e9).round() / 1e9


def check_values(frame: pl.DataFrame, path: Path, required: tuple[str, ...] = ("t", "u", "v", "w")) -> None:
    """Refuse the first empty, non-finite or out-of-range value where values
    enter: ``t`` (s) within ``MAX_ABS_TIME_S``, every other float within
    ``MAX_ABS_VALUE``; the ``required`` columns present in every row, optional
    columns possibly empty."""
    bounds = {name: MAX_ABS_VALUE for name in ("u", "v", "w")} | {"t": MAX_ABS_TIME_S}
    bounds |= {name: MAX_ABS_VALUE for name in (*OPTIONAL_FLOATS, *required) if name != "t"}
    checked = [name for name in bounds if name in frame.columns and not _within(frame[name], bounds[name])]
    if not checked:
        return
    first_bad = frame.select(
        (pl.col(name).cast(pl.Float64).is_nan() | (pl.col(name).cast(pl.Float64).abs() > bounds[name]))
        .fill_null(name in required)
        .arg_true().first().alias(name)
        for name in checked
    ).row(0)
    for name, row in zip(checked, first_bad):
        if row is not None:
            raise InputError(f"column {name!r}, row {row + 1} {_fault(frame[name][row], bounds[name], name)}", path=path)


def _within(values: pl.Series, bound: float) -> bool:
    """True if a float column without nulls lies within ``±bound`` (its
    extremes, two passes, no copy; NaN fails); False sends it to the row
    by row search for the fault (as does any other column)."""
    if values.dtype != pl.Float64 or values.null_count() or not len(values):
        return False
    array = values.to_numpy()
    return bool(array.max() <= bound and array.min() >= -bound)


def check_references(frame: pl.DataFrame, path: Path) -> None:
    """Refuse jig references ``gx, gy, gz`` that are not unit vectors in g
    (within ``REFERENCE_TOLERANCE``) in every row that has one (docs/inputs.md),
    saying what the column looks like: a file's gyroscope, or accelerations in m/s^2."""
    given = [c for c in REFERENCES if c in frame.columns]
    if not given:
        return
    norm = pl.sum_horizontal(pl.col(c).fill_null(0.0) ** 2 for c in given).sqrt()
    some = pl.any_horizontal(pl.col(c).is_not_null() for c in given)
    bad = frame.select(((norm - 1.0).abs() > REFERENCE_TOLERANCE) & some).to_series().fill_null(False).arg_true()
    if not len(bad):
        return
    row = int(bad[0])
    peaks = {c: float(frame[c].abs().max() or 0.0) for c in given}  # type: ignore[arg-type]
    column = max(peaks, key=lambda c: peaks[c])
    length = float(frame.select(norm)[row, 0])
    looks = ("accelerations in m/s^2? references are in g" if abs(length / 9.80665 - 1.0) < 0.05
             else "a gyroscope or another sensor's column?")
    raise InputError(f"reference column {column!r} holds values up to {peaks[column]:.4g}, not unit vectors in g "
                     f"(row {row + 1}: |(gx, gy, gz)| = {length:.4g}): {looks}", path=path,
                     hint="map only the columns you mean in dataset.toml [format] columns")


def _fault(value: float | None, bound: float, name: str) -> str:
    if value is None:
        return "is empty"
    if math.isnan(value):
        return "is NaN"
    if math.isinf(value):
        return f"is {value}"
    return f"is {value:.10g}, beyond ±{bound:g}{' s' if name == 't' else ''}"


def label_columns(
    frame: pl.DataFrame, spec: CaptureSpec | None, path: Path, label_source: str = "file"
) -> pl.DataFrame:
    """Canonical sample columns of one capture.

    ``frame`` has ``t`` (s) or ``t_ns``, ``u, v, w`` and any optional columns
    of docs/inputs.md, whose labels came from ``label_source``; ``spec`` supplies
    labels the file lacks.
    """
    check_values(frame, path)
    check_references(frame, path)
    if "t_ns" not in frame.columns:
        frame = frame.with_columns(t_ns=nanoseconds(pl.col("t")))
    back: list[int] | pl.Series = [] if frame["t_ns"].is_sorted() else frame["t_ns"].diff().lt(0).arg_true()
    if len(back):
        row = int(back[0])
        raise InputError(
            f"time goes backwards at row {row + 1} "
            f"({frame['t_ns'][row] / 1e9:.6f} s after {frame['t_ns'][row - 1] / 1e9:.6f} s)",
            path=path,
        )
    labelled_in_file = "axis" in frame.columns or "rate_hz" in frame.columns
    canonical = "axis" in frame.columns and (frame["axis"].is_in(AXES) | frame["axis"].is_null()).all()
    if "axis" in frame.columns and not canonical:  # new strings only where some label needs it
        frame = frame.with_columns(pl.col("axis").str.strip_chars().str.to_lowercase())
        bad = frame["axis"].is_not_null() & ~frame["axis"].is_in(AXES)
        if bad.any():
            row = int(bad.arg_true()[0])
            raise InputError(
                f"unknown axis label {frame['axis'][row]!r} at row {row + 1} (expected x, y or z)", path=path
            )
    spec = spec or CaptureSpec(file=path.name)
    fills = {"axis": spec.axis, "rate_hz": spec.rate_hz}
    frame = frame.with_columns(
        (pl.lit(value) if name not in frame.columns else pl.col(name).fill_null(value)).alias(name)
        for name, value in fills.items()
        if value is not None or name not in frame.columns
    )
    frame = frame.with_columns(pl.col("rate_hz").cast(pl.Float64))
    if "angle_deg" not in frame.columns and spec.theta0_deg is not None and spec.rate_hz is not None:
        elapsed_s = (pl.col("t_ns") - pl.col("t_ns").first()).cast(pl.Float64) / 1e9
        frame = frame.with_columns(angle_deg=spec.theta0_deg + 360.0 * spec.rate_hz * elapsed_s)
    frame = frame.with_columns(
        pl.lit(None, pl.Float64).alias(c) for c in OPTIONAL_FLOATS if c not in frame.columns
    ).with_columns(rate_hz=canonical_rate(pl.col("rate_hz")))
    pose = pl.col("pose").str.strip_chars() if "pose" in frame.columns else pl.lit(None, pl.String)
    has_labels = pl.col("axis").is_not_null() | pl.col("rate_hz").is_not_null()
    source = label_source if labelled_in_file else ("toml" if spec.axis or spec.rate_hz is not None else None)
    all_labelled = frame.select(has_labels.all()).item()
    frame = frame.with_columns(
        pose=pl.when(pose.is_in(POSES)).then(pose).otherwise(None),
        label_source=pl.lit(source, pl.String) if all_labelled else pl.when(has_labels).then(pl.lit(source, pl.String)).otherwise(None),
        capture=pl.lit(spec.file),
    )
    return frame.select(pl.col(c).cast(t) for c, t in schema("samples").polars_schema.items())
