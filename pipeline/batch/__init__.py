"""Batch stage: scheduled runs over capture directories."""
