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
    t = samples["t_ns"].to_numpy()
    steps = np.diff(t)
    steps = steps[steps > 0]
    return float(np.median(steps)) / 1e9 if steps.size else 0.0


def _split(t_ns: np.ndarray, resid: np.ndarray, dt_s: float) -> list[np.ndarray]:
    """``resid`` (n, 3) cut at the logger's pauses."""
    cuts = np.flatnonzero(np.diff(t_ns) > GAP_FACTOR * dt_s * 1e9) + 1
    return [p for p in np.split(resid, cuts) if p.shape[0] >= 2]


def residual_pieces(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame, dwells: pl.DataFrame,
                    dt_s: float) -> list[np.ndarray]:
    """Every contiguous piece (n_i, 3) of residuals of u, v, w: the fitted
    static and rotation segments and the labelled poses; where there are
    none, the dwells the stillness detector found (a dwell inside a hand
    move carries the hand's motion, so it serves only an unlabelled
    recording)."""
    pieces: list[np.ndarray] = []
    ok = fits.filter(pl.col("status") == "ok")
    done: set[int] = set()
    for (segment,), rows in ok.group_by(["segment"], maintain_order=True):
        part = samples.filter(pl.col("segment") == segment)
        if part.height < 2 or rows.height != len(CHANNELS) or part["angle_deg"].null_count():
            continue
        rows = rows.sort(pl.col("channel").replace_strict({c: i for i, c in enumerate(CHANNELS)}))
        theta = np.deg2rad(part["angle_deg"].to_numpy())
        rate, fitted = rows["rate_hz"][0], rows["rate_fit_hz"][0]
        if rate and fitted is not None and np.isfinite(fitted):  # the four-parameter fit's rate
            theta = theta[0] + fitted / rate * (np.unwrap(theta) - theta[0])
        z = np.column_stack([np.ones_like(theta), np.sin(theta), np.cos(theta)])
        coef = rows.select("C", "A", "B").to_numpy()  # (channel, C A B)
        y = part.select(CHANNELS).to_numpy()
        pieces += _split(part["t_ns"].to_numpy(), y - z @ coef.T, dt_s)
        done.add(int(segment))
    for segment in segments.filter(pl.col("kind") == "pose")["segment"]:
        part = samples.filter(pl.col("segment") == segment)
        y = part.select(CHANNELS).to_numpy()
        if y.shape[0] >= 2:
            pieces += _split(part["t_ns"].to_numpy(), y - y.mean(axis=0), dt_s)
            done.add(int(segment))
    for row in dwells.iter_rows(named=True) if not pieces else ():
        if row["segment"] in done:
            continue
        part = samples.filter(pl.col("t_ns").is_between(row["t_start_ns"], row["t_end_ns"]))
        y = part.select(CHANNELS).to_numpy()
        if y.shape[0] >= 2:
            pieces += _split(part["t_ns"].to_numpy(), y - y.mean(axis=0), dt_s)
    return pieces
