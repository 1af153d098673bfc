"""Table labels checked against each other before anything is fitted: a
rotation segment's commanded angle must advance at 360 degrees per turn,
``360 rate_hz`` degrees per second. An ``angle_deg`` column written in
radians advances 57.3 times slower, a ``rate_hz`` in rad/s or in rpm
disagrees by 2 pi or 60; fitted as given, each gives a wrong result with
no finding (the sine fit follows the angles). Refused with the likely
cause instead."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl

from rotcal.errors import InputError

# the angles' rate over the commanded one outside these bounds is a unit mistake, not a table's error
RATIO_BOUNDS = (0.8, 1.25)
# the likely cause of a ratio near each of these (angle rate / (360 rate_hz)), the nearest (radians,
# 1/57.3, and rpm, 1/60, are 4.7 % apart; a table's angles follow its rate far closer)
_CAUSES = ((np.pi / 180.0, "angle_deg in radians?"), (1.0 / 60.0, "rate_hz in rpm?"), (1.0 / (2.0 * np.pi), "rate_hz in rad/s?"),
           (1.0 / 60.0, "rate_hz in rpm?"), (2.0 * np.pi, "rate_hz in turns per second of 2 pi rad?"),
           (-1.0, "the angle turns against rate_hz's sign?"))


def check_angle_rates(samples: pl.DataFrame, root: Path) -> None:
    """Refuse the first rotation segment whose angles advance at a rate
    other than ``360 rate_hz`` deg/s (the median over its successive
    samples, so that wraps and a few jittery stamps do not count), naming
    the capture and the likely cause. Segments without angles pass."""
    if "angle_deg" not in samples.columns or samples.height < 2:
        return
    same = (pl.col("segment") == pl.col("segment").shift()) & (pl.col("rate_hz") != 0)
    steps = samples.lazy().select(
        pl.col("segment"), pl.col("capture"), pl.col("rate_hz"),
        speed=pl.col("angle_deg").diff() / (pl.col("t_ns").diff().cast(pl.Float64) / 1e9),
        keep=same & pl.col("t_ns").diff().gt(0) & pl.col("angle_deg").diff().is_not_null(),
    ).filter(pl.col("keep")).group_by("segment").agg(
        pl.col("capture").first(), pl.col("rate_hz").first(), pl.col("speed").median(), n=pl.len(),
    ).filter(pl.col("n") >= 3).sort("segment").collect()
    if steps.is_empty():
        return
    ratio = steps["speed"].to_numpy() / (360.0 * steps["rate_hz"].to_numpy())
    bad = np.flatnonzero(~((ratio >= RATIO_BOUNDS[0]) & (ratio <= RATIO_BOUNDS[1])))
    if bad.size == 0:
        return
    k = int(bad[0])
    r = float(ratio[k])
    distance, cause = min((abs(np.log(r / factor)) if r * factor > 0 else np.inf, text) for factor, text in _CAUSES)
    if distance > np.log(RATIO_BOUNDS[1]):
        cause = "angle_deg and rate_hz disagree (units, or labels of another segment?)"

    raise InputError(f"capture {steps['capture'][k]}: the table angle advances {steps['speed'][k]:.4g} deg/s where "
                     f"rate_hz {steps['rate_hz'][k]:g} commands {360.0 * steps['rate_hz'][k]:.4g} deg/s "
                     f"({r:.3g} times): {cause}", path=root)


def partial_angles(samples: pl.DataFrame, segments: pl.DataFrame) -> tuple[str, ...]:
    """A warning per table segment whose angles are missing in some samples
    only (an empty ``angle_deg`` cell): such a segment is fitted without
    the table's angles, which should not pass unsaid."""
    if "angle_deg" not in samples.columns:
        return ()
    table = segments.filter(pl.col("kind").is_in(["static", "rotation"]) & (pl.col("angle_source") == "none"))["segment"]
    if table.is_empty():
        return ()
    counts = (samples.lazy().filter(pl.col("segment").is_in(table.to_list()))
              .group_by("segment").agg(pl.col("capture").first(), missing=pl.col("angle_deg").null_count(), n=pl.len())
              .filter((pl.col("missing") > 0) & (pl.col("missing") < pl.col("n"))).sort("segment").collect())
    return tuple(f"capture {capture}, segment {segment}: {missing} of {n} samples have no angle_deg, so the segment is "
                 "fitted without the table's angles (fill the empty cells, or leave the column out)"
                 for segment, capture, missing, n in counts.iter_rows())
