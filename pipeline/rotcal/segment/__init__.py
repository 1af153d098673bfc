"""Segment stage: samples -> segments. From labels (file columns,
``[[capture]]``, table channel, poses: ``segment_by_labels``), and from the
signals alone where labels are missing (stillness, constant rotations, step
sequences: ``infer_segments``)."""

from __future__ import annotations

from rotcal.segment.labelled import segment_by_labels
from rotcal.segment.unlabelled import infer_segments

__all__ = ["infer_segments", "segment_by_labels"]
