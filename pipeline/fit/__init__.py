"""Fit stage: per-segment sine fits (rotations) and step fits (static positions)."""
