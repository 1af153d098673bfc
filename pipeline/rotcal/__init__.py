"""rotcal: rotation-table calibration of three-axis accelerometers."""

import os

__version__ = "0.1.0"

# Polars' allocator (jemalloc) keeps freed pages for a second or more before
# returning them; rotcal's stages alternate polars and numpy, which cannot
# reuse them, so on captures of millions of samples they add up to the peak
# memory. Returned at once instead (read when polars is first imported; a
# setting of the user's own is kept). Batch pool workers, which run many
# small datasets one after another, keep them a second
# (``batch.jobs.WORKER_MALLOC``).
JEMALLOC_CONF = "dirty_decay_ms:0,muzzy_decay_ms:0"
USER_JEMALLOC_CONF = os.environ.get("_RJEM_MALLOC_CONF")  # the user's own, kept everywhere
os.environ.setdefault("_RJEM_MALLOC_CONF", JEMALLOC_CONF)

# The Python API (rotcal.api) from the package itself, loaded when first used:
# `import rotcal` and the command line's start-up stay free of the stages.
# (named apart from the subpackages rotcal.run, rotcal.apply and rotcal.simulate)
_API = ("Applied", "Calibration", "Export", "Quantity", "RateCalibration", "Recording", "Result", "apply_calibration",
        "calibrate", "correct", "export_calibration", "load_calibration", "load_dataset", "open_results",
        "simulate_dataset")


def __getattr__(name: str) -> object:
    if name in _API:
        from rotcal import api

        return getattr(api, name)
    raise AttributeError(f"module 'rotcal' has no attribute {name!r}")
