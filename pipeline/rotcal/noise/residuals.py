"""The residuals of the fitted model, per channel, in contiguous pieces: a
static step sequence's and a rotation's samples minus their segment's sine
fit (C + A sin theta + B cos theta at the fitted rate), a labelled pose's
and each other dwell's samples minus their mean. A piece ends where the logger paused (a gap of more than
1.5 sample intervals), so the Allan variance never averages across a pause."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS

GAP_FACTOR = 1.5


def sample_interval_s(samples: pl.DataFrame) -> float:
    """The recording's sample interval: the median of the stamps' steps."""
    steps = samples["t_ns"].diff()
    median = steps.filter(steps > 0).median()
    return float(median) / 1e9 if median is not None else 0.0  # type: ignore[arg-type]


def _segment_rows(samples: pl.DataFrame) -> dict[int, tuple[int, int]]:
    """(first row, row count) of every segment: its samples are one contiguous
    run (the fit stage's reading; kept here so that the noise stage imports no stage)."""
    runs = samples.select(pl.col("segment").rle()).unnest("segment")
    lengths = runs["len"].to_numpy()
    starts = np.cumsum(lengths) - lengths
    return {int(seg): (int(a), int(k)) for seg, a, k in zip(runs["value"], starts, lengths) if seg is not None}


def split_at_pauses(t_ns: np.ndarray, resid: np.ndarray, dt_s: float) -> list[np.ndarray]:
    """``resid`` (n, 3) cut at the logger's pauses."""
    cuts = np.flatnonzero(np.diff(t_ns) > GAP_FACTOR * dt_s * 1e9) + 1
    return [p for p in np.split(resid, cuts) if p.shape[0] >= 2]


def fit_residual_pieces(t_ns: np.ndarray, y: np.ndarray, angle_deg: np.ndarray, coef: np.ndarray, rate_hz: float,
                        rate_fit_hz: float | None, dt_s: float) -> list[np.ndarray] | None:
    """One fitted segment's residual pieces (its stamps, channels (n, 3),
    angles and fitted coefficients (channel x (C, A, B)) at its commanded
    and fitted rates), or None where its angles do not serve."""
    theta = np.deg2rad(angle_deg)
    if t_ns.size < 2 or not np.isfinite(theta).all():
        return None
    if rate_hz and rate_fit_hz is not None and np.isfinite(rate_fit_hz):  # the four-parameter fit's rate
        theta = theta[0] + rate_fit_hz / rate_hz * (np.unwrap(theta) - theta[0])
    z = np.column_stack([np.ones_like(theta), np.sin(theta), np.cos(theta)])
    del theta
    resid = z @ coef.T
    del z
    return split_at_pauses(t_ns, np.subtract(y, resid, out=resid), dt_s)


def residual_pieces(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame, dwells: pl.DataFrame,
                    dt_s: float) -> list[np.ndarray]:
    """Every contiguous piece (n_i, 3) of residuals of u, v, w: the fitted
    static and rotation segments and the labelled poses; where there are
    none, the dwells the stillness detector found (a dwell inside a hand
    move carries the hand's motion, so it serves only an unlabelled
    recording)."""
    pieces: list[np.ndarray] = []
    rows_of = _segment_rows(samples)
    t_ns = samples["t_ns"].to_numpy()
    y_all = samples.select(CHANNELS).to_numpy()
    angle = samples["angle_deg"].to_numpy() if "angle_deg" in samples.columns else None
    order = {c: i for i, c in enumerate(CHANNELS)}
    coefs: dict[int, np.ndarray] = {}
    rates: dict[int, tuple[float, float | None]] = {}
    for seg, channel, rate, fitted, c, a, b in fits.filter(pl.col("status") == "ok").select(
            "segment", "channel", "rate_hz", "rate_fit_hz", "C", "A", "B").iter_rows():
        coefs.setdefault(int(seg), np.full((len(CHANNELS), 3), np.nan))[order[channel]] = (c, a, b)
        rates[int(seg)] = (rate, fitted)
    done: set[int] = set()
    for segment, coef in coefs.items():
        if segment not in rows_of or angle is None or not np.isfinite(coef).all():
            continue
        first, count = rows_of[segment]
        fitted_pieces = fit_residual_pieces(t_ns[first:first + count], y_all[first:first + count],
                                            angle[first:first + count], coef, *rates[segment], dt_s)
        if fitted_pieces is None:
            continue
        pieces += fitted_pieces
        done.add(segment)
    for segment in segments.filter(pl.col("kind") == "pose")["segment"]:
        if segment not in rows_of:
            continue
        first, count = rows_of[segment]
        y = y_all[first:first + count]
        if count >= 2:
            pieces += split_at_pauses(t_ns[first:first + count], y - y.mean(axis=0), dt_s)
            done.add(int(segment))
    for row in dwells.iter_rows(named=True) if not pieces else ():
        if row["segment"] in done:
            continue
        inside = (t_ns >= row["t_start_ns"]) & (t_ns <= row["t_end_ns"])
        y = y_all[inside]
        if y.shape[0] >= 2:
            pieces += split_at_pauses(t_ns[inside], y - y.mean(axis=0), dt_s)
    return pieces
