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

from rotcal.combine.channels import channel_fault
from rotcal.combine.labelled import segment_coefficients
from rotcal.combine.multiposition import OrientationFreeFit, orientation_free
from rotcal.combine.phasefree import PhaseFreeFit, PhaseSegment, solve_phase_free
from rotcal.fit import OffsetCovariance
from rotcal.fit.means import modelled_poses, with_segment_offsets
from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table
from rotcal.segment.stillness import unused_rows

SINGLE_POSE = ("a single pose outside every step sequence, which give the static result (dwells.parquet lists it with "
               "its segment)")
CONSISTENCY = 1e-3  # chi-square p-value below which the components measured twice disagree


def _phase_free_fits(fits: pl.DataFrame, own_phase: frozenset[int], g_local: float, g_uncertainty: float
                     ) -> list[tuple[float, list[PhaseSegment], PhaseFreeFit | Failure]]:
    """Per rate with rotation segments fitted against their own phase: the
    rate, its segments (those with a table angle fixed) and their solution."""
    rotating = fits.filter((pl.col("kind") == "rotation") & (pl.col("status") == "ok"))
    solved = []
    for rate in sorted(set(rotating.filter(pl.col("segment").is_in(list(own_phase)))["rate_hz"].to_list())):
        segs = [PhaseSegment(s.segment, s.axis, s.coef, s.cov, s.segment not in own_phase, s.dof)
                for s in segment_coefficients(rotating.filter(pl.col("rate_hz") == rate))]
        solved.append((rate, segs, solve_phase_free(rate, segs, g_local, g_uncertainty)))
    return solved


def reduce_phase_free(fits: pl.DataFrame, own_phase: frozenset[int], g_local: float, g_uncertainty: float) -> Reduction:
    """Every rate that has rotation segments fitted against their own phase,
    with a warning where the components measured twice disagree."""
    results: list[IntrinsicResult] = []
    failures: list[Failure] = []
    warnings = []
    for rate, _, solved in _phase_free_fits(fits, own_phase, g_local, g_uncertainty):
        if isinstance(solved, Failure):
            failures.append(solved)
            continue
        results.append(solved.result)
        if solved.dof > 0 and chdtrc(solved.dof, solved.chi2) < CONSISTENCY:
            warnings.append(f"rate {rate:g} Hz: the components measured twice disagree beyond their uncertainties "
                            f"(chi-square {solved.chi2:.3g} on {solved.dof} degrees of freedom)")
    return Reduction("table", tuple(results), tuple(failures), (), tuple(warnings))


def segment_phases(fits: pl.DataFrame, segments: pl.DataFrame, own_phase: frozenset[int], g_local: float,
                   g_uncertainty: float, clock_factor: float) -> pl.DataFrame:
    """Each own-phase rotation segment's table angle as the phase-free
    solution gives it: theta = sigma_k (theta_k + phi), phi = 360 f (t -
    t_phase) the segment's own phase (``rotcal.fit.sinefit``; f the rate it
    was fitted at, before the clock correction ``clock_factor`` the fits'
    rates carry) and theta_k, sigma_k solved by ``rotcal.combine.phasefree``.
    Columns segment, theta_k_deg, theta_k_u_deg, sigma (+-1), phase_rate_hz
    (f) and t_phase_ns; rates whose solution failed have no rows."""
    rows = [(s.segment, float(solved.theta_deg[k]), float(solved.theta_u_deg[k]), -1.0 if solved.reflected[k] else 1.0)
            for _, segs, solved in _phase_free_fits(fits, own_phase, g_local, g_uncertainty)
            if isinstance(solved, PhaseFreeFit) for k, s in enumerate(segs) if not s.fixed]
    solved = pl.DataFrame(rows, schema={"segment": pl.Int32, "theta_k_deg": pl.Float64, "theta_k_u_deg": pl.Float64,
                                        "sigma": pl.Float64}, orient="row")
    rate = fits.unique("segment", keep="first").select("segment", phase_rate_hz=pl.col("rate_fit_hz") / clock_factor)
    return (solved.join(rate, on="segment", how="left")
            .join(segments.select("segment", "t_phase_ns"), on="segment", how="left").sort("segment"))


def reduce_dwells(dwells: pl.DataFrame, need_static: bool, g_local: float, g_uncertainty: float,
                  single: frozenset[int] = frozenset(), rejected: pl.DataFrame | None = None,
                  samples: pl.DataFrame | None = None, offsets: OffsetCovariance | None = None) -> Reduction:
    """The static result (rate 0) from the dwells when ``need_static``, and
    the ``dwells`` table (with |a| after calibration when they gave it);
    otherwise the dwells of ``single`` (segments of one pose, outside every
    step sequence) are not used. Every still interval not used (those and
    the detector's ``rejected`` ones) is listed in ``still_unused`` and
    counted in a warning. ``samples``: the recording's, the dwells' means
    then weighed as static poses are, by their covariance between dwells
    from the noise model and the wander their scatter shows
    (``fit.means.modelled_poses``), and with what the table segments'
    offsets showed over the record where ``offsets`` (``fit.wander``,
    ``fit.means.with_segment_offsets``)."""
    from rotcal.combine.static import with_unused  # here: static imports the pose machinery this module need not

    results: tuple[IntrinsicResult, ...] = ()
    failures: tuple[Failure, ...] = ()
    idle = dwells.filter(pl.col("segment").is_in(list(single))) if not need_static and dwells.height else dwells.clear()
    parts = [unused_rows(str(idle["dataset"][0]), idle["capture"], idle.with_columns(reason=pl.lit(SINGLE_POSE)), 0.0
                         ).with_columns(rest_s=idle["dwell_s"])
             ] if idle.height else []
    parts += [rejected] if rejected is not None and rejected.height else []
    fault = channel_fault(dwells) if need_static and dwells.height else None
    if fault is not None:
        failures = (Failure(0.0, f"static dwells: {fault}"),)
    elif need_static and dwells.height:
        dwells, between = (dwells, None) if samples is None else modelled_poses(samples, dwells)
        if between is not None and offsets is not None:
            dwells, between = with_segment_offsets(dwells, between, offsets)
        fit = orientation_free(dwells.rename({"dwell": "pose"}), g_local, g_uncertainty, between=between)
        if isinstance(fit, OrientationFreeFit):
            results = (fit.result,)
            dwells = dwells.with_columns(g_magnitude=pl.Series(fit.magnitude))
        else:
            failures = (Failure(0.0, f"static dwells: {fit.reason}"),)
    reduction = Reduction("intrinsic", results, failures, (Table("dwells", dwells),) if dwells.height else (), ())
    if not parts:
        return reduction
    return with_unused(reduction, pl.concat(parts).sort("t_start_ns"), dwells.height - idle.height)
