"""Metrology stage: fits and intrinsic results -> the tables a lab signs:
uncertainty budget and Monte Carlo (GUM and its Supplement 1), Geist 2017's
simultaneous solution and consistency checks, Gaitan 2021's estimators, the
frequency response, cross-sensitivity matrices and AN4399 corrections."""

from __future__ import annotations

from rotcal.metrology.an4399 import correction_frame, correction_uncertainty_frame, corrections_from_poses, temperature_frame
from rotcal.metrology.consistency import consistency_frame, consistency_note
from rotcal.metrology.crosssens import cross_sensitivity_frame, matrix_intrinsic
from rotcal.metrology.gaitan import gaitan_frame
from rotcal.metrology.response import frequency_response_frame
from rotcal.metrology.simultaneous import simultaneous, simultaneous_frame
from rotcal.metrology.uncertainty import budget_frame, monte_carlo, monte_carlo_frame, monte_carlo_note

__all__ = ["budget_frame", "consistency_frame", "consistency_note", "correction_frame", "correction_uncertainty_frame", "corrections_from_poses", "cross_sensitivity_frame", "frequency_response_frame", "gaitan_frame", "matrix_intrinsic", "monte_carlo", "monte_carlo_frame", "monte_carlo_note", "simultaneous", "simultaneous_frame", "temperature_frame"]
