"""rotcal: rotation-table calibration of three-axis accelerometers."""

__version__ = "0.1.0"
