"""Fit stage: samples and segments -> fits. Per-segment sine fits of
constant rotations and step fits of static positions (``fit_segments``,
``fits_frame``); the four-parameter and own-phase sine fits; the shared
least-squares wrapper (``lsq``); the offsets' covariance
between segments (``OffsetCovariance``, ``fit.wander``)."""

from __future__ import annotations

from rotcal.fit.segments import SegmentFit, fit_segments, fits_frame
from rotcal.fit.wander import OffsetCovariance

__all__ = ["OffsetCovariance", "SegmentFit", "fit_segments", "fits_frame"]
