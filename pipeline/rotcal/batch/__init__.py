"""Batch: scheduled runs over capture directories (``run_batch``):
discovery and fingerprints (``plan``), jobs on a local pool or Dask
(``jobs``), the run manifest and lock (``manifest``), the run loop and its
atomic publication (``runner``)."""

from __future__ import annotations

from rotcal.batch.runner import BatchSummary, Reporter, run_batch

__all__ = ["BatchSummary", "Reporter", "run_batch"]
