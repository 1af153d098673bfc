"""The reductions of segments without an angle reference (docs/conventions.md:
a segment without angle_deg has an unknown theta0), found by
``rotcal.segment.unlabelled``:

- per rate, the rotation segments fitted against their own phase go to
  ``rotcal.combine.phasefree`` (segments of the rate that do have a table
  angle enter with their phase fixed); the result is in the table frame;
- the dwells (rate 0) go to ``rotcal.combine.multiposition.orientation_free``
  when no labelled static sequence gives the static result; the result is in
  the intrinsic frame (u along x, v in the x-y plane).
"""

from __future__ import annotations

import polars as pl
from scipy.special import chdtrc

from rotcal.combine.labelled import segment_coefficients
from rotcal.combine.multiposition import OrientationFreeFit, orientation_free
from rotcal.combine.phasefree import PhaseSegment, solve_phase_free
from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table

CONSISTENCY = 1e-3  # chi-square p-value below which the components measured twice disagree


def reduce_phase_free(fits: pl.DataFrame, own_phase: frozenset[int], g_local: float, g_uncertainty: float) -> Reduction:
    """Every rate that has rotation segments fitted against their own phase,
    with a warning where the components measured twice disagree."""
    results: list[IntrinsicResult] = []
    failures: list[Failure] = []
    warnings = []
    rotating = fits.filter((pl.col("kind") == "rotation") & (pl.col("status") == "ok"))
    for rate in sorted(set(rotating.filter(pl.col("segment").is_in(list(own_phase)))["rate_hz"].to_list())):
        segs = segment_coefficients(rotating.filter(pl.col("rate_hz") == rate))
        solved = solve_phase_free(rate, [PhaseSegment(s.segment, s.axis, s.coef, s.cov, s.segment not in own_phase, s.dof)
                                         for s in segs], g_local, g_uncertainty)
        if isinstance(solved, Failure):
            failures.append(solved)
            continue
        results.append(solved.result)
        if solved.dof > 0 and chdtrc(solved.dof, solved.chi2) < CONSISTENCY:
            warnings.append(f"rate {rate:g} Hz: the components measured twice disagree beyond their uncertainties "
                            f"(chi-square {solved.chi2:.3g} on {solved.dof} degrees of freedom)")
    return Reduction("table", tuple(results), tuple(failures), (), tuple(warnings))


def reduce_dwells(dwells: pl.DataFrame, need_static: bool, g_local: float, g_uncertainty: float) -> Reduction:
    """The static result (rate 0) from the dwells when ``need_static``, and
    the ``dwells`` table (with |a| after calibration when they gave it)."""
    results: tuple[IntrinsicResult, ...] = ()
    failures: tuple[Failure, ...] = ()
    if need_static and dwells.height:
        fit = orientation_free(dwells.rename({"dwell": "pose"}), g_local, g_uncertainty)
        if isinstance(fit, OrientationFreeFit):
            results = (fit.result,)
            dwells = dwells.with_columns(g_magnitude=pl.Series(fit.magnitude))
        else:
            failures = (Failure(0.0, f"static dwells: {fit.reason}"),)
    return Reduction("intrinsic", results, failures, (Table("dwells", dwells),) if dwells.height else (), ())
