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
# signed integer outputs whose overflow wraps a value near +2^(W-1) to near -2^(W-1) between two samples
WRAP_BITS = (16, 24, 32)
WRAP_NEAR = 0.75  # both samples of a wrap beyond this fraction of the limit, of opposite signs
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
    within = _within(frame, bounds)
    present = set(frame.columns)
    checked = [name for name in bounds if name in present and name not in within]
    if not checked:
        check_wraparound(frame, path)
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
    check_wraparound(frame, path)


def check_wraparound(frame: pl.DataFrame, path: Path) -> None:
    """Refuse a channel whose value jumps between the two ends of a signed
    W-bit range from one sample to the next (``WRAP_BITS``): an integer
    output that overflowed (an offset near 2^(W-1), or counts stored in too
    few bits), which no accelerometer's signal does; the poses, steps and
    fits would read the jumps as motion. Channels that stay within 3/4 of
    2^15 (every sensor's usual counts) cost one pass for their extreme."""
    names = [c for c in ("u", "v", "w") if c in frame.columns and frame.schema[c].is_numeric()]
    if not names or frame.height < 2:
        return
    peaks = frame.select(pl.col(names).cast(pl.Float64).abs().max()).row(0)
    for name, peak in zip(names, peaks):
        for bits in WRAP_BITS:
            limit = 2.0 ** (bits - 1)
            if peak is None or peak <= WRAP_NEAR * limit or peak > limit:
                continue
            y = pl.col(name).cast(pl.Float64)
            near = (y.abs() > WRAP_NEAR * limit) & (y.abs() <= limit)
            jump = frame.select((near & near.shift(1) & (y * y.shift(1) < 0)).arg_true().first()).item()
            if jump is not None:
                before, after = frame[name][jump - 1], frame[name][jump]
                raise InputError(f"column {name!r} jumps from {before:.10g} to {after:.10g} between rows {jump} and "
                                 f"{jump + 1}: a signed {bits}-bit integer output wrapping around at ±2^{bits - 1} "
                                 "(an offset near the limit, or counts stored in too few bits)", path=path,
                                 hint="store the counts in a wider integer, or unwrap them before the run")


def _within(frame: pl.DataFrame, bounds: dict[str, float]) -> set[str]:
    """The float columns without nulls that lie within their ``±bound``, by
    their extremes and their sum (which NaN makes NaN: the extremes skip
    it), in one select of three passes per column without a copy, the
    columns in parallel; any other column goes to the row by row search
    for the fault."""
    types = frame.schema  # built anew at each access: once, not per name
    names = [name for name in bounds if types.get(name) == pl.Float64 and not frame[name].null_count()]
    if not names or not frame.height:
        return set()
    stats = frame.select(pl.col(names).min().name.suffix(" min"), pl.col(names).max().name.suffix(" max"),
                         pl.col(names).sum().name.suffix(" sum")).row(0)
    lows, highs, totals = stats[:len(names)], stats[len(names):2 * len(names)], stats[2 * len(names):]
    return {n for n, low, high, total in zip(names, lows, highs, totals)
            if -bounds[n] <= low and high <= bounds[n] and math.isfinite(total)}


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
    shown = f"{value:.10g}" if float(f"{value:.10g}") == value else f"{value:.17g}"  # every digit it has
    if name == "t":
        return (f"is {shown}, beyond ±{bound:g} s: time stamps in ms, us or ns? set dataset.toml [format] "
                "time_unit (docs/inputs.md)")
    return f"is {shown}, beyond ±{bound:g}"


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
    labelled_in_file = "axis" in frame.columns or "rate_hz" in frame.columns
    relabel = "axis" in frame.columns and not _canonical(frame["axis"])
    if relabel and "t_ns" not in frame.columns:  # the time check comes before the labels'
        frame = frame.with_columns(t_ns=nanoseconds(pl.col("t")))
    if "t_ns" in frame.columns:
        _check_time_order(frame["t_ns"], path)
    if relabel:  # new strings only where some label needs it
        frame = frame.with_columns(pl.col("axis").str.strip_chars().str.to_lowercase())
        bad = frame["axis"].is_not_null() & ~frame["axis"].is_in(AXES)
        if bad.any():
            row = int(bad.arg_true()[0])
            raise InputError(
                f"unknown axis label {frame['axis'][row]!r} at row {row + 1} (expected x, y or z)", path=path
            )
    spec = spec or CaptureSpec(file=path.name)
    axis, rate = _filled(frame, "axis", spec.axis), _filled(frame, "rate_hz", spec.rate_hz).cast(pl.Float64)
    columns = {name: pl.col(name) if name in frame.columns else pl.lit(None, pl.Float64) for name in OPTIONAL_FLOATS}
    t_ns = pl.col("t_ns") if "t_ns" in frame.columns else nanoseconds(pl.col("t"))  # computed with the others
    if "angle_deg" not in frame.columns and spec.theta0_deg is not None and spec.rate_hz is not None:
        elapsed_s = (t_ns - t_ns.first()).cast(pl.Float64) / 1e9
        columns["angle_deg"] = spec.theta0_deg + 360.0 * spec.rate_hz * elapsed_s
    pose = pl.col("pose").str.strip_chars() if "pose" in frame.columns else pl.lit(None, pl.String)
    has_labels = axis.is_not_null() | rate.is_not_null()
    source = label_source if labelled_in_file else ("toml" if spec.axis or spec.rate_hz is not None else None)
    all_labelled = frame.select(has_labels.all()).item()
    columns |= {"capture": pl.lit(spec.file), "t_ns": t_ns, "u": pl.col("u"), "v": pl.col("v"), "w": pl.col("w"),
                "axis": axis, "rate_hz": canonical_rate(rate), "pose": pl.when(pose.is_in(POSES)).then(pose).otherwise(None),
                "label_source": pl.lit(source, pl.String) if all_labelled
                else pl.when(has_labels).then(pl.lit(source, pl.String)).otherwise(None)}
    # one select: the columns are computed in parallel, no intermediate table
    samples = frame.select(columns[c].cast(t).alias(c) for c, t in schema("samples").polars_schema.items())
    if "t_ns" not in frame.columns:
        _check_time_order(samples["t_ns"], path)
    return samples


def _canonical(axis: pl.Series) -> bool:
    """Whether every axis label is x, y, z or empty (by its type alone for
    labels parsed into the sample table's Enum)."""
    if isinstance(axis.dtype, pl.Enum) and set(axis.dtype.categories) <= set(AXES):
        return True
    return bool((axis.is_in(AXES) | axis.is_null()).all())


def _check_time_order(t_ns: pl.Series, path: Path) -> None:
    """Refuse the first sample earlier than the one before it."""
    # compared with the one before, not differenced: a difference may pass 2^63 ns and wrap
    back: list[int] | pl.Series = [] if t_ns.is_sorted() else (t_ns < t_ns.shift(1)).fill_null(False).arg_true()
    if len(back):
        row = int(back[0])
        raise InputError(f"time goes backwards at row {row + 1} ({t_ns[row] / 1e9:.6f} s after {t_ns[row - 1] / 1e9:.6f} s)",
                         path=path)


def _filled(frame: pl.DataFrame, name: str, value: object) -> pl.Expr:
    """Column ``name`` with ``value`` (a ``[[capture]]`` label) where it is empty, or
    ``value`` alone where the capture has no such column."""
    if name not in frame.columns:
        return pl.lit(value)
    return pl.col(name) if value is None else pl.col(name).fill_null(value)
