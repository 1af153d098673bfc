"""The physical constants of docs/conventions.md that the dataset metadata
needs, in a module that loads nothing: the batch process reads every
dataset.toml (``ingest.meta``) while its workers start, and numpy (0.23 s of
CPU) would take a core from them."""

STANDARD_GRAVITY = 9.80665  # m/s^2, the conventional value (3rd CGPM, 1901)
STANDARD_GRAVITY_UNCERTAINTY = 0.02  # m/s^2: g_local where dataset.toml gives none (docs/conventions.md)
