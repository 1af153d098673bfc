"""Time-base stage: each capture's stamps against a regular sampling grid
(duplicates, repeated stamps, missing samples, gaps, jitter), repaired where
possible (``repair_timebase``: samples -> samples and findings; once the
segments are known, ``classify_gaps`` calls the gaps between them pauses), and the
logger clock against the plan's nominal rates (``rates``)."""

from __future__ import annotations

from rotcal.timebase.check import findings_frame
from rotcal.timebase.repair import classify_gaps, repair_timebase

__all__ = ["classify_gaps", "findings_frame", "repair_timebase"]
