"""Combine stage: per-rate intrinsic parameters from the fits (labelled, phase-free and static reductions)."""
