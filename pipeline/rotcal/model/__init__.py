"""What every stage shares: the conventions (``conventions``), the forward
model (``physics``) with the effect catalogue (``effects``), and the result
records (``results``: one constructor of intrinsic results, one failure
record, one reduction record).

This module imports nothing, so reading a dataset's metadata
(``ingest.meta``, which takes standard gravity from ``conventions``) loads
no part of the model."""
