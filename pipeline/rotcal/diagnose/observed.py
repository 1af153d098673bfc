"""The samples the diagnosis models: a dataset's fitted table segments as
``Observations``, long segments thinned to a bounded total."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.diagnose.geometry import Observations
from rotcal.fit.segments import segment_rows
from rotcal.model.physics import AXES, CHANNELS, Motion


def kept_per_segment(counts: np.ndarray, max_samples: int) -> np.ndarray:
    """How many samples of each segment the model keeps: all of every segment
    when the total is within ``max_samples``, else the same number c from
    each segment longer than c, with c chosen so that the total is
    ``max_samples`` (short segments, the static steps, are kept whole)."""
    if counts.sum() <= max_samples:
        return counts
    ordered = np.sort(counts)
    below = np.r_[0, np.cumsum(ordered)[:-1]]  # samples in the segments shorter than each
    cap = (max_samples - below) / (ordered.size - np.arange(ordered.size))  # c if it lies between neighbours
    return np.minimum(counts, int(cap[np.argmax(ordered >= cap)]))


def thinned_rows(first: np.ndarray, count: np.ndarray, max_samples: int) -> np.ndarray:
    """The sample numbers the diagnosis models of the segments starting at
    sample ``first`` with ``count`` samples: each thinned evenly to its share
    (``kept_per_segment``), ``first + floor(i n / k)``. A capture read block
    by block gathers these rows for the diagnosis (``blockwise.segments``)."""
    kept = kept_per_segment(count, max_samples)
    return np.concatenate([a + np.floor(np.arange(k) * (n / k)).astype(np.int64) for a, n, k in zip(first, count, kept)]
                          or [np.zeros(0, np.int64)])


def observations(samples: pl.DataFrame, segments: pl.DataFrame, fits: pl.DataFrame,
                 rates: list[float], g_local: float, max_samples: int) -> tuple[Observations, np.ndarray, int] | None:
    """The samples of the fitted table segments at the determined ``rates``
    (in the order given), sorted by rate then time, each static sample's step
    number (-1 during rotation), and how many samples there were in all.

    Beyond ``max_samples`` each long segment is thinned to evenly spaced
    samples (``kept_per_segment``): the model stays exact, the noise of its
    estimates grows as the square root of the thinning, and memory stays
    bounded on captures of millions of samples. The model's rotation runs
    at ``phase_rate_hz`` where the samples have it (angles reconstructed
    from a fitted phase, ``reconstructed``), at ``rate_hz`` otherwise.
    """
    fitted = (fits["status"] == "ok").fill_null(False).to_numpy() & np.isin(fits["rate_hz"].to_numpy(), rates)
    ok = np.unique(fits["segment"].to_numpy()[fitted]).tolist()
    wanted = set(ok)  # each one's kind and start (null where ``segments`` lacks it):
    described = {s: (kind, start) for s, kind, start in zip(*(segments[c].to_list() for c in ("segment", "kind", "t_start_ns")))
                 if s in wanted}
    if not described:
        return None
    rows = segment_rows(samples)
    first, count = (np.array([rows[k][i] for k in ok], dtype=np.int64) for i in (0, 1))
    kept = kept_per_segment(count, max_samples)
    index = thinned_rows(first, count, max_samples)
    kind, start_ns = zip(*(described.get(k, (None, None)) for k in ok))
    static, rotating, start_s = (np.repeat(v, kept) for v in (np.array(kind) == "static", np.array(kind) == "rotation",
                                                              np.array(start_ns, dtype=float) / 1e9))
    motion_rate = "phase_rate_hz" if "phase_rate_hz" in samples.columns else "rate_hz"
    # each float column as an array (no copy without nulls; NaN for null), the kept rows taken once; the labels taken first
    column = {c: samples[c].to_numpy() for c in ("t_ns", "rate_hz", "angle_deg", "temperature_c", motion_rate, *CHANNELS)}
    segment, axis = (samples.select(pl.col("segment"), pl.col("axis").cast(pl.Enum(AXES)).to_physical())[index]
                     .get_column(c).to_numpy() for c in ("segment", "axis"))
    t_ns, rate, angle = (column[c][index] for c in ("t_ns", "rate_hz", "angle_deg"))
    rate_idx = np.zeros(index.size, dtype=np.int64)
    for i, r in enumerate(rates):
        rate_idx[rate == r] = i
    # a static step: a run of one segment at one angle, numbered in time order (NaN equals NaN within a run)
    same = (segment[1:] == segment[:-1]) & ((angle[1:] == angle[:-1]) | (np.isnan(angle[1:]) & np.isnan(angle[:-1])))
    step = np.where(static, np.r_[0, np.cumsum(~same)], -1)
    # rates in contiguous blocks (each segment stays contiguous): the per-rate normal equations then work on views
    order = np.lexsort((t_ns, rate_idx))
    taken = index[order]
    temperature = column["temperature_c"][taken].astype(float)  # NaN where not logged
    motion = Motion(
        t_s=t_ns[order] / 1e9,
        axis_idx=axis[order].astype(np.int64),
        rotating=rotating[order],
        theta_cmd_deg=angle[order],
        t_start_s=start_s[order],
        rate_hz=column[motion_rate][taken],
        t0_s=int(column["t_ns"].min()) / 1e9,
        # the DUT temperature where every sample has one and it varies (a constant one carries no evidence)
        temperature_c=temperature if temperature.size and np.ptp(temperature) > 0 else None,
    )
    y = np.asfortranarray(np.column_stack([column[c][taken] for c in CHANNELS]))  # the layout of a frame's to_numpy
    obs = Observations(motion, y, rate_idx[order], np.array(rates), segment[order], g_local)
    return obs, step[order], int(count.sum())
