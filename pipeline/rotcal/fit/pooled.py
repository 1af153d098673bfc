"""What only a recording's segments together measure, applied to each
segment's own fit (``fit.segments.segment_fit``): the noise's spectrum
pooled over all segments (``fit.spectrum``) and the offsets' wander between
them (``fit.wander``), with the recording's noise model from the fits'
residuals (``rotcal.noise``) where some offset's noise is coloured. A run
in memory and a run block by block call the same functions."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from rotcal.fit.spectrum import spectrum_widened
from rotcal.fit.wander import RecordNoise, offset_floor
from rotcal.model.physics import CHANNELS
from rotcal.noise.allan import PooledAllan, pooled_avars
from rotcal.noise.means import process_of
from rotcal.noise.model import identify_channel

SegmentFit = Any  # ``fit.segments.SegmentFit`` (not imported: that module imports this one)


def across_segments(fits: list[SegmentFit], t_first_s: np.ndarray, t_last_s: np.ndarray, kinds: list[tuple[str, float]],
                    axes: list[str | None], noise_of: Callable[[list[SegmentFit]], RecordNoise | None],
                    modelled: bool, record_start_s: float | None = None) -> list[SegmentFit]:
    """The fits (each segment's own, ``segment_fit``) widened by what only
    all segments together measure: the noise's spectrum pooled over them
    (``fit.spectrum``) and the offsets' wander between them (``fit.wander``),
    the segments' spans in seconds ``t_first_s`` to ``t_last_s``;
    ``noise_of(fits)``, the recording's noise model, is asked for only where
    some offset's noise is coloured (white noise: its cost spared);
    ``record_start_s``: where a random walk starts (``fit.wander``)."""
    fits = spectrum_widened(fits)
    coloured = any(f.noise_ratio is not None and np.any(f.noise_ratio[0] > 1.0) for f in fits)
    axis_of: list[object] = list(axes)
    return offset_floor(fits, (t_first_s + t_last_s) / 2, t_last_s - t_first_s, kinds, axis_of,
                        noise_of(fits) if coloured else None, modelled=modelled,
                        record_start_s=record_start_s)


def record_noise_pooled(pooled: PooledAllan, dt_s: float, record_s: tuple[float, float]) -> RecordNoise | None:
    """``record_noise`` from the pieces' Allan sums pooled as they came
    (``noise.allan.PooledAllan``: a capture read block by block)."""
    if not pooled.sizes:
        return None
    allan = pooled.result(1 / dt_s)
    channels = [identify_channel(c, [], 1 / dt_s, "", allan[r], pooled.sizes) for r, c in enumerate(CHANNELS)]
    if all(ch.reason for ch in channels):
        return None
    return RecordNoise(tuple(process_of(ch) for ch in channels), dt_s, record_s)


def record_noise(pieces: list[list[np.ndarray]], dt_s: float, record_s: tuple[float, float]) -> RecordNoise | None:
    """The recording's noise model (``rotcal.noise``: each channel's Allan
    variance of the fits' residuals fitted with the IEEE Std 952 terms) as
    the offsets' covariance needs it; None where no channel could be
    modelled (too few averaging times)."""
    flat = [p for ps in pieces for p in ps]
    if not flat:
        return None
    allan = pooled_avars(flat, 1 / dt_s)
    channels = [identify_channel(c, [p[:, r] for p in flat], 1 / dt_s, "", allan[r]) for r, c in enumerate(CHANNELS)]
    if all(ch.reason for ch in channels):
        return None
    return RecordNoise(tuple(process_of(ch) for ch in channels), dt_s, record_s)
