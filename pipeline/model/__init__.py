"""Conventions, the forward model and the result records every stage shares."""
