"""The block path: one capture through the run's first stages a block of
samples at a time, in memory bounded by the block and the longest segment,
not by the capture (docs/streaming.md). It is the run for every single
capture whose format has a block reader (``ingest.formats.REGISTRY``,
``can_stream``); its tables are those of the same stage functions on the
samples held whole.

In the order a run calls them:

- ``load``: the dataset, its capture opened as blocks
  (``ingest.formats.blocks.open_stream``, each format's ``blocks`` module),
  or read whole with the reason (``load.why_not`` and the list in
  ``load``'s docstring: the one place that says what needs the whole
  capture, and why);
- ``repaired``: the blocks after the time base, checked on the stamps alone
  (``grid``: the grid fitted from sums additive over blocks; ``ranks``:
  exact medians in bounded memory; ``timebase``: the outcome and its
  repair of each block);
- ``segments``: the label runs across block boundaries and their fits, each
  segment held whole while it is fitted by ``fit.segments.segment_fit``,
  with the samples the later stages keep (the diagnosis's thinned rows,
  asked of ``diagnose.observed``; the static steps; the sums of Geist's
  simultaneous solution; the noise model's pooled residual statistics).
"""
