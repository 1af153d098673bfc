"""Fit stage: samples and segments -> fits. Per-segment sine fits of
constant rotations and step fits of static positions (``fit_segments``,
``fits_frame``); the four-parameter and own-phase sine fits; the shared
least-squares wrapper (``lsq``)."""

from __future__ import annotations

from rotcal.fit.segments import fit_segments, fits_frame

__all__ = ["fit_segments", "fits_frame"]
