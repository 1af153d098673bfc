"""One dataset through every stage: ingest -> time base -> segment (labels,
then the signals for what labels leave out) -> fit -> combine, and the
result tables written into the output directory. The CLI and the batch
runner both call ``run_dataset``; neither holds pipeline logic."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import polars as pl
from threadpoolctl import threadpool_limits

from rotcal.combine.labelled import CombineFailure, IntrinsicResult, combine, components_frame, intrinsic_frame
from rotcal.combine.multiposition import PoseFailure
from rotcal.combine.poses import table_step_poses
from rotcal.combine.static import StaticReduction, reduce_static
from rotcal.config import RunConfig
from rotcal.errors import UndeterminedError
from rotcal.fit.segments import fit_segments, fits_frame
from rotcal.ingest import load_dataset
from rotcal.metrology.an4399 import correction_frame, correction_uncertainty_frame, corrections_from_poses, temperature_frame
from rotcal.metrology.consistency import consistency_frame, consistency_note
from rotcal.metrology.crosssens import cross_sensitivity_frame
from rotcal.metrology.gaitan import gaitan_frame
from rotcal.metrology.response import frequency_response_frame
from rotcal.metrology.simultaneous import simultaneous, simultaneous_frame
from rotcal.metrology.uncertainty import budget_frame, monte_carlo, monte_carlo_frame, monte_carlo_note
from rotcal.segment.labelled import segment_by_labels
from rotcal.segment.unlabelled import infer_segments, reduce_unreferenced
from rotcal.tables import write_parquet
from rotcal.timebase.check import findings_frame, repair_timebase

if TYPE_CHECKING:
    from rotcal.diagnose import Diagnosis


@dataclass(frozen=True, eq=False)
class RunOutcome:
    """What a run produced: results per rate, warnings (failed segments or
    rates), notes (defaults applied) and the files written."""

    dataset: str
    output_unit: str
    results: tuple[IntrinsicResult, ...]
    warnings: tuple[str, ...]
    notes: tuple[str, ...]
    written: tuple[Path, ...]
    diagnosis: Diagnosis | None = None
    static: StaticReduction | None = None


def run_dataset(path: Path, out: Path, meta_path: Path | None = None, config: RunConfig = RunConfig()) -> RunOutcome:
    """Run the pipeline on one dataset (see ``_run``) with BLAS on one thread:
    rotcal's parallelism is across segments and datasets, and a threaded BLAS
    on small matrices competing with it costs more than it gives."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(Path(path), Path(out), meta_path, config)


def _run(path: Path, out: Path, meta_path: Path | None, config: RunConfig) -> RunOutcome:
    """Run the pipeline on one dataset and write its tables into ``out``.

    Raises ``InputError`` for unreadable input and ``UndeterminedError`` when
    what remains after failed segments cannot determine any rate's result
    (the segment and fit tables, with the failure rows, are written first).
    """
    ds = load_dataset(path, meta_path, config.limits, config.run.workers)
    timebase = repair_timebase(ds.samples, ds.name)
    samples, segments = segment_by_labels(timebase.samples, ds.name, ds.meta.angle_source)
    inferred = infer_segments(samples, segments, ds.name, ds.meta.plan_rates_hz, timebase.unrepairable)
    # a table recording (labelled or found in the signals); otherwise the static path below
    table = not inferred.segments.filter(pl.col("kind").is_in(["static", "rotation"])).is_empty()
    own_phase = inferred.own_phase if table else frozenset()
    if table:
        samples, segments = inferred.samples, inferred.segments
    referenced = segments.filter(pl.col("angle_source") != "none")
    fits = fits_frame(fit_segments(samples, referenced, config.fit, config.run.workers)
                      + (list(inferred.fits) if table else []), segments, ds.name)
    written = [write_parquet(segments, out / "segments.parquet", "segments"),
               write_parquet(fits, out / "fits.parquet", "fits"),
               write_parquet(pl.concat([timebase.findings, findings_frame(list(inferred.findings) if table else [])]),
                             out / "timebase.parquet", "timebase")]
    labelled_fits = fits.filter(~pl.col("segment").is_in(list(own_phase)))
    combined = combine(labelled_fits, ds.meta.g_local, ds.meta.g_local_uncertainty)
    unreferenced, consistency = [], []
    if table:
        static_labelled = any(isinstance(r, IntrinsicResult) and r.rate_hz == 0 for r in combined)
        unreferenced, dwells, consistency = reduce_unreferenced(fits, own_phase, inferred.dwells, not static_labelled,
                                                                ds.meta.g_local, ds.meta.g_local_uncertainty)
        if dwells.height:
            written.append(write_parquet(dwells, out / "dwells.parquet", "dwells"))
    replaced = {r.rate_hz for r in unreferenced}
    combined = sorted([r for r in combined if r.rate_hz not in replaced] + unreferenced, key=lambda r: (abs(r.rate_hz), r.rate_hz))
    results = tuple(r for r in combined if isinstance(r, IntrinsicResult))
    failed = fits.filter(fits["status"] == "failed").unique("segment", keep="first", maintain_order=True)
    warnings = tuple(
        list(timebase.warnings) + (list(inferred.warnings) + consistency if table else [])
        + [f"segment {s} ({a}, {r:g} Hz): {why}" for s, a, r, why in failed.select("segment", "axis", "rate_hz", "reason").iter_rows()]
        + [f"rate {f.rate_hz:g} Hz not determined: {f.reason}" for f in combined if isinstance(f, CombineFailure)]
    )
    notes = ds.notes + (inferred.notes if table else ())
    static = None
    if not results and not table:
        static = reduce_static(samples, segments, ds.name, ds.meta.g_local, ds.meta.g_local_uncertainty)
        if isinstance(static, PoseFailure):
            raise UndeterminedError(f"no table segments, and the static poses cannot be reduced: {static.reason}", path=path)
        results = (static.result,)
    if not results:
        if not warnings:
            raise UndeterminedError("no static or rotation segments: the samples carry no axis and rate labels", path=path)
        more = f" (and {len(warnings) - 1} more problems)" if len(warnings) > 1 else ""
        raise UndeterminedError(f"no rate can be determined: {warnings[0]}{more}", path=path)
    unit = ds.meta.output_unit
    intrinsic = intrinsic_frame(list(results), ds.name, "baseline", unit)
    # per-segment components, and issue 3's tables, exist only where the segments' phases are the table's
    labelled_results = [r for r in results if r.rate_hz not in replaced]
    # issue 3's tables before the diagnosis, whose imports and figures then stay in memory; listed in their place
    metrology = (_metrology_tables(samples, labelled_fits, labelled_results, ds.name, unit, ds.meta.g_local,
                                   ds.meta.g_local_uncertainty, out, config)
                 if static is None and labelled_results else ([], []))
    diagnosis = None
    if replaced:
        notes += ("diagnosis skipped: segments without a table angle (its models need the angle)",)
    elif config.diagnosis.enabled and static is None:
        from rotcal.diagnose import diagnose  # scipy.stats loads when diagnosing, after the large stages

        diagnosis = diagnose(samples, segments, fits, results, ds.name, unit, ds.meta.g_local_uncertainty,
                             ds.meta.angle_source == "measured", config.diagnosis)
    if diagnosis is not None:
        if diagnosis.final.obs.n < diagnosis.samples_available:
            notes += (f"diagnosis modelled {diagnosis.final.obs.n:,} of the {diagnosis.samples_available:,} samples "
                      f"(long segments thinned evenly; [diagnosis] max_samples)",)
        intrinsic = intrinsic.vstack(intrinsic_frame(list(diagnosis.refined), ds.name, "refined", unit))
        written += [write_parquet(diagnosis.findings, out / "diagnosis.parquet", "diagnosis"),
                    write_parquet(diagnosis.parameters, out / "effect_parameters.parquet", "effect_parameters")]
        if config.diagnosis.report:
            from rotcal.report.diagnosis import write_report  # matplotlib only when a report is wanted

            written.append(write_report(diagnosis, fits, results, ds.name, unit, out, config.report.figures))
    written.append(write_parquet(intrinsic, out / "intrinsic.parquet", "intrinsic"))
    if static is None:
        written.append(write_parquet(components_frame(labelled_fits, labelled_results, ds.name),
                                     out / "components.parquet", "components"))
    # the dwells' orientation-free result is in the intrinsic frame; phase-free rotations in the table's
    frames = [static.frame if static is not None else "intrinsic" if r.rate_hz == 0 and r.rate_hz in replaced else "table"
              for r in results]
    written.append(write_parquet(
        cross_sensitivity_frame(list(zip(results, frames)), ds.name, "baseline", unit, ds.meta.g_local_uncertainty),
        out / "cross_sensitivity.parquet", "cross_sensitivity"))
    corrections, correction_warnings = corrections_from_poses(table_step_poses(samples, segments) if static is None else static.positions)
    warnings += tuple(correction_warnings)
    if corrections:
        written += [write_parquet(correction_frame(corrections, ds.name, unit), out / "correction.parquet", "correction"),
                    write_parquet(correction_uncertainty_frame(corrections, ds.name, unit),
                                  out / "correction_uncertainty.parquet", "correction_uncertainty")]
        by_temperature = temperature_frame(corrections, ds.name, unit)
        if not by_temperature.is_empty():
            written.append(write_parquet(by_temperature, out / "correction_temperature.parquet", "correction_temperature"))
    written += metrology[0]
    notes = list(notes) + metrology[1]
    if static is not None:
        written.append(write_parquet(static.check, out / "poses.parquet", "poses"))
    return RunOutcome(ds.name, unit, results, warnings, tuple(notes), tuple(written), diagnosis, static)


def _metrology_tables(samples: pl.DataFrame, fits: pl.DataFrame, results: list[IntrinsicResult], dataset: str,
                      unit: str, g: float, u_g: float, out: Path, config: RunConfig) -> tuple[list[Path], list[str]]:
    """Issue 3's tables of a table (step or rotation) dataset: uncertainty
    budget, Geist's simultaneous solution and consistency checks, Gaitan's
    estimators, the frequency response with its plot, and the optional Monte
    Carlo; with the notes they give."""
    consistency = consistency_frame(fits, g, dataset, unit)
    response = frequency_response_frame(results, fits, dataset, unit)
    both = [r for r in simultaneous(samples, fits, g, u_g, config.fit.sine_fit == "four_parameter") if isinstance(r, IntrinsicResult)]
    written = [
        write_parquet(budget_frame(results, dataset, unit), out / "uncertainty_budget.parquet", "uncertainty_budget"),
        write_parquet(simultaneous_frame(both, results, dataset, unit), out / "simultaneous.parquet", "simultaneous"),
        write_parquet(consistency, out / "consistency.parquet", "consistency"),
        write_parquet(gaitan_frame(fits, g, u_g, dataset, unit), out / "gaitan_estimators.parquet", "gaitan_estimators"),
        write_parquet(response, out / "frequency_response.parquet", "frequency_response"),
    ]
    if config.report.figures:
        from rotcal.report.plot import frequency_response_png  # matplotlib only when there is a plot to draw

        png = frequency_response_png(response, out / "frequency_response.png", dataset)
        written += [png] if png else []
    notes = [n for n in [consistency_note(consistency)] if n]
    if config.uncertainty.monte_carlo:
        mc = monte_carlo_frame(monte_carlo(fits, g, u_g, config.uncertainty), results, dataset, unit)
        written.append(write_parquet(mc, out / "monte_carlo.parquet", "monte_carlo"))
        notes.append(monte_carlo_note(mc))
    return written, notes
