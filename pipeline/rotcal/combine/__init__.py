"""Combine stage: fits -> intrinsic results per rate. Three reductions,
each returning one ``Reduction`` record: labelled table segments
(``reduce_labelled``, Geist 2017), rotations without a phase reference and
dwells (``reduce_phase_free``, ``reduce_dwells``), and static poses
(``reduce_static``), from samples or pose summaries (``summary_poses``)."""

from __future__ import annotations

from rotcal.combine.labelled import intrinsic_frame, reduce_labelled
from rotcal.combine.poses import summary_poses, table_step_poses
from rotcal.combine.static import StaticReduction, reduce_static
from rotcal.combine.unreferenced import reduce_dwells, reduce_phase_free

__all__ = ["StaticReduction", "intrinsic_frame", "reduce_dwells", "reduce_labelled", "reduce_phase_free", "reduce_static", "summary_poses",
           "table_step_poses"]
