"""The simulator: plans, DUT draws, effects and writers of synthetic recordings."""
