"""Segment stage: segments from labels, from stillness, and from the signals alone."""
