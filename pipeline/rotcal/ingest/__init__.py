"""Ingest: one dispatcher from a dataset (a directory or a single capture
file, with its ``dataset.toml``) to the canonical sample table
(``dataset.load_dataset``). Nothing downstream knows which format a sample
came from.

This module imports nothing: the batch process finds and hashes the
captures (``files``, ``meta``) without loading polars or the readers, so its
pool starts sooner."""
