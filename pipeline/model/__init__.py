"""What every stage shares: the conventions (``conventions``), the forward
model (``physics``) with the effect catalogue (``effects``), and the result
records (``results``: one constructor of intrinsic results, one failure
record, one reduction record)."""

from __future__ import annotations

from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table

__all__ = ["Failure", "IntrinsicResult", "Reduction", "Table"]
