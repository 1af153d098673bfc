"""Resource package (installed as ``rotcal_configs``): default run configuration and dataset metadata for known recordings."""
