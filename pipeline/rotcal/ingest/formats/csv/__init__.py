"""CSV captures (docs/inputs.md, "CSV captures"): ``reader`` (one file, any
logger's layout through ``[format]``, found by ``layout``), ``joined`` (a
dataset of plain CSV files in one parse) and ``writer`` (a sample table as
CSV, as the simulator writes it)."""
