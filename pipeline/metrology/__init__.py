"""Metrology stage: uncertainty budgets, Monte Carlo, simultaneous solution, consistency, Gaitan's estimators, frequency response, cross-sensitivity, AN4399 corrections."""
