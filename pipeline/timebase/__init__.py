"""Time-base stage: each capture's stamps against a regular sampling grid
(duplicates, repeated stamps, missing samples, gaps, jitter), repaired where
possible (``repair_timebase``: samples -> samples and findings), and the
logger clock against the plan's nominal rates (``rates``)."""

from __future__ import annotations

from rotcal.timebase.check import findings_frame, repair_timebase

__all__ = ["findings_frame", "repair_timebase"]
