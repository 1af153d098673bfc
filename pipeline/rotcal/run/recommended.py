"""The run's stage adapters after the results: the diagnosis, the
``intrinsic`` table, the recommended model, the segment fits under it (the
refit), the metrology tables of that model and AN4399's corrections; each
reads what ``stages`` produced (``Segmented``, ``Reductions``, the results)."""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from rotcal.blockwise.load import corrected_blocks, streamed_fits
from rotcal.blockwise.segments import StreamedSegments
from rotcal.combine import StaticReduction, intrinsic_frame, table_step_poses
from rotcal.combine.labelled import rate_segments
from rotcal.combine.unreferenced import segment_phases
from rotcal.config import RunConfig
from rotcal.fit import fit_segments, fits_frame
from rotcal.fit.quantization import coarse_steps
from rotcal.ingest.dataset import Dataset
from rotcal.metrology import (
    budget_frame,
    consistency_frame,
    consistency_note,
    correction_frame,
    correction_uncertainty_frame,
    corrections_from_poses,
    frequency_response_frame,
    gaitan_frame,
    monte_carlo,
    monte_carlo_frame,
    monte_carlo_note,
    simultaneous,
    simultaneous_frame,
    temperature_frame,
)
from rotcal.metrology.simultaneous import simultaneous_from_sums
from rotcal.model.calibration import BASELINE, REFINED, Recommended, recommend
from rotcal.model.results import IntrinsicResult, Reduction, Table
from rotcal.run.outputs import Figure
from rotcal.run.stages import Reductions, Segmented

if TYPE_CHECKING:
    from rotcal.combine.heldout import HeldOut
    from rotcal.diagnose import Diagnosis
    from rotcal.diagnose.static import StaticDiagnosis


def diagnose_stage(seg: Segmented, reductions: Reductions, results: tuple[IntrinsicResult, ...], ds: Dataset,
                   config: RunConfig) -> tuple[Diagnosis | StaticDiagnosis | None, tuple[str, ...]]:
    """The diagnosis of a recording, with its notes: a static one's from its
    poses (``diagnose.static``); a table recording's from its segments, where
    rotation segments without a table angle enter with the angle
    reconstructed from their solved phases (``diagnose.reconstructed``) and
    results in another frame than the table's (static dwells of unknown
    orientation) are not diagnosed."""
    if reductions.static is not None:
        return static_diagnosis_stage(seg, reductions.static, ds, config), ()
    if not config.diagnosis.enabled:
        return None, ()
    from rotcal.diagnose import diagnose  # the diagnosis loads when diagnosing, after the large stages

    in_table = {rate for r in reductions.all if r.frame == "table" for rate in r.rates}
    notes = []
    if len(in_table) < len(results):
        notes.append("diagnosis without the static dwells of unknown orientation (their result is not in the table frame)")
    phases = None
    if reductions.unreferenced_rates & in_table:
        g, u_g, clock = ds.meta.g_local, ds.meta.g_local_uncertainty, seg.clock_factor
        phases = segment_phases(seg.fits, seg.segments, seg.own_phase, g, u_g, clock)
        notes.append(f"diagnosis on table angles reconstructed from the solved phases of {phases.height} rotation "
                     "segment(s) without one; rate_error not tested (the fitted rates absorb it)")
    diagnosed = tuple(r for r in results if r.rate_hz in in_table)
    samples = seg.samples if seg.streamed is None else _diagnosed_samples(seg.streamed, seg.fits, diagnosed, config)
    coarse = coarse_steps(samples, seg.fits, ds.meta.output_unit)  # a step is not physics
    if coarse is not None:
        return None, (coarse,)
    diagnose_with = partial(diagnose, samples, seg.segments, seg.fits,
                            diagnosed, ds.name, ds.meta.output_unit,
                            ds.meta.g_local_uncertainty, ds.meta.angle_source == "measured", config.diagnosis,
                            random_walk=_random_walk(seg, ds.meta.output_unit))
    if phases is None:
        diagnosis = diagnose_with(None)
    else:
        from rotcal.diagnose.phases import jointly_diagnosed, phases_without_effects

        diagnosis = jointly_diagnosed(diagnose_with, partial(phases_without_effects, seg.samples, seg.segments, seg.fits,
                                                             own_phase=seg.own_phase, g_local=g, g_uncertainty=u_g,
                                                             clock_factor=clock), phases)
    if diagnosis is None:
        return None, ()
    if seg.streamed is not None:  # the samples the thinned rows stand for
        diagnosis = replace(diagnosis, samples_available=seg.streamed.count(_diagnosed(seg.fits, diagnosed)))
    if diagnosis.final.obs.n < diagnosis.samples_available:
        notes.append(f"diagnosis modelled {diagnosis.final.obs.n:,} of the {diagnosis.samples_available:,} "
                     f"samples (long segments thinned evenly; [diagnosis] max_samples)")
    return diagnosis, tuple(notes)


def _random_walk(seg: Segmented, output_unit: str) -> tuple[float, ...]:
    """The noise model's random walk coefficient K per channel (``rotcal.noise``:
    the residuals' Allan variance), 0 where a channel has none; none where
    the model cannot be identified (the offsets' floor is then their noise)."""
    try:
        model = seg.noise_model(output_unit)
    except np.linalg.LinAlgError:
        return ()
    return tuple(next((t.value for t in ch.terms if t.term == "random_walk"), 0.0) for ch in model.channels)


def _diagnosed(fits: pl.DataFrame, results: tuple[IntrinsicResult, ...]) -> frozenset[int]:
    """The segments ``diagnose.observed.observations`` models: the ok fits at the diagnosed rates."""
    rates = [r.rate_hz for r in results]
    return frozenset(fits.filter((pl.col("status") == "ok") & pl.col("rate_hz").is_in(rates))["segment"].to_list())


def _diagnosed_samples(streamed: StreamedSegments, fits: pl.DataFrame, results: tuple[IntrinsicResult, ...],
                       config: RunConfig) -> pl.DataFrame:
    """A streamed capture's samples the diagnosis models: the rows
    ``diagnose.observed.observations`` thins its segments to, gathered (within
    ``[diagnosis] max_samples`` it keeps them all) with the capture's first
    sample (the model's time origin)."""
    return streamed.diagnosed_samples(_diagnosed(fits, results), config.diagnosis.max_samples)


def static_diagnosis_stage(seg: Segmented, static: StaticReduction, ds: Dataset,
                           config: RunConfig) -> StaticDiagnosis | None:
    """The diagnosis of a static recording's poses (``diagnose.static``)."""
    if not config.diagnosis.enabled:
        return None
    from rotcal.diagnose.static import diagnose_static  # loaded when diagnosing a static recording

    t_ns = seg.samples["t_ns"]
    return diagnose_static(static, None if t_ns.is_empty() else int(t_ns.to_numpy().min()), ds.name, ds.meta.output_unit,
                           ds.meta.g_local_uncertainty, config.diagnosis)


def intrinsic_table(results: tuple[IntrinsicResult, ...], diagnosis: Diagnosis | StaticDiagnosis | None, ds: Dataset,
                    static: StaticReduction | None) -> pl.DataFrame:
    """The ``intrinsic`` rows: baseline (or a static recording's most general
    determined model), its nested models, and refined by the diagnosis."""
    unit = ds.meta.output_unit
    intrinsic = intrinsic_frame(list(results), ds.name, BASELINE if static is None else static.model, unit)
    for name, nested in () if static is None else static.nested:
        intrinsic = intrinsic.vstack(intrinsic_frame([nested], ds.name, name, unit))
    if diagnosis is not None:
        intrinsic = intrinsic.vstack(intrinsic_frame(list(diagnosis.refined), ds.name, "refined", unit))
    return intrinsic


def baseline_reason(diagnosis: Diagnosis | StaticDiagnosis | None, reductions: Reductions, config: RunConfig,
                    diagnosis_notes: tuple[str, ...]) -> str:
    """Why the baseline model is the result when it is: what the diagnosis found, or why it did not run."""
    if diagnosis is not None:
        return getattr(diagnosis, "heldout", "") or "the diagnosis found no effect to model"
    why = (diagnosis_notes[0] if diagnosis_notes else "switched off ([diagnosis] enabled = false)"
           if not config.diagnosis.enabled else "the static poses leave no degree of freedom to test an effect"
           if reductions.static is not None else "no fitted table segments")
    return f"diagnosis not run: {why.removeprefix('diagnosis skipped: ')}"


def recommend_stage(intrinsic: pl.DataFrame, results: tuple[IntrinsicResult, ...], frames: tuple[str, ...],
                    diagnosis: Diagnosis | StaticDiagnosis | None, reductions: Reductions, config: RunConfig,
                    diagnosis_notes: tuple[str, ...]) -> Recommended:
    """The recommended model with its results (``model.calibration.recommend``):
    refined where the diagnosis modelled effects, a static recording's
    nested model where the F test chooses it, the baseline otherwise."""
    static = reductions.static
    others = {REFINED: diagnosis.refined if diagnosis else (), **{n: (r,) for n, r in (static.nested if static else ())}}
    modelled = tuple(diagnosis.before) if diagnosis else ()  # the modelled findings
    reason = baseline_reason(diagnosis, reductions, config, diagnosis_notes)
    held = table_held_out(diagnosis)
    if held is not None:  # the refined model earns its place only by predicting held-out segments
        verdict, unit = held
        reason = verdict.text(BASELINE, REFINED, unit)
        if not verdict.better:
            reason = f"{reason}: {', '.join(modelled)} not modelled in the recommended result"
            modelled = ()
    return recommend(intrinsic, results, frames, others, modelled, reason, static.chosen if static else None)


def table_held_out(diagnosis: Diagnosis | StaticDiagnosis | None) -> tuple[HeldOut, str] | None:
    """A table diagnosis' refined model against the baseline on held-out
    segments (``diagnose.heldout``), where it modelled an effect."""
    final = getattr(diagnosis, "final", None)
    if final is None or not diagnosis or not diagnosis.refined:
        return None
    from rotcal.diagnose.heldout import segments_held_out

    return segments_held_out(final)


def correction_stage(seg: Segmented, static: StaticReduction | None, ds: Dataset) -> tuple[list[Table], tuple[str, ...]]:
    """AN4399's correction tables from the static positions (a table recording's steps, or the static poses), with their warnings."""
    positions = table_step_poses(seg.samples, seg.segments) if static is None else static.positions
    corrections, warnings = corrections_from_poses(positions)
    if not corrections:
        return [], tuple(warnings)
    dataset, unit = ds.name, ds.meta.output_unit
    tables = [Table("correction", correction_frame(corrections, dataset, unit)),
              Table("correction_uncertainty", correction_uncertainty_frame(corrections, dataset, unit))]
    by_temperature = temperature_frame(corrections, dataset, unit)
    return tables + ([Table("correction_temperature", by_temperature)] if not by_temperature.is_empty() else []), tuple(warnings)


def recommended_fits(seg: Segmented, diagnosis: Diagnosis | StaticDiagnosis | None, chosen: Recommended, ds: Dataset,
                     config: RunConfig) -> pl.DataFrame:
    """The segment fits under the recommended model: under the refined one,
    those of the samples less its modelled effects (``diagnose.corrected``)."""
    if chosen.model == BASELINE or diagnosis is None or not seg.table:   # a static recording has no segment fits
        return seg.labelled_fits
    from rotcal.diagnose import Diagnosis
    from rotcal.diagnose.corrected import without_effects

    assert isinstance(diagnosis, Diagnosis)  # a static recording's returned above
    if seg.streamed is not None:
        fits = streamed_fits(corrected_blocks(seg.streamed, seg.segments, seg.fits, diagnosis), ds, config)
        return fits_frame(fits, seg.segments, ds.name)
    samples = without_effects(seg.samples, seg.segments, seg.fits, diagnosis)
    referenced = seg.segments.filter(pl.col("angle_source") != "none")
    return fits_frame(fit_segments(samples, referenced, config.fit, config.run.workers), seg.segments, ds.name)


def metrology_stage(seg: Segmented, labelled: Reduction | None, chosen: Recommended, chosen_fits: pl.DataFrame,
                    ds: Dataset, config: RunConfig) -> tuple[list[Table | Figure], tuple[str, ...]]:
    """The metrology tables of a table (step or rotation) dataset: uncertainty
    budget, Geist's simultaneous solution and consistency checks, Gaitan's
    estimators, the frequency response with its plot, and the optional Monte
    Carlo; with the notes they give. They exist only for the rates of the
    segments whose phases are the table's (the labelled reduction). The
    consistency checks and the frequency response are those of the
    recommended model (its results; ``chosen_fits``, the segment fits under
    it); the budget, the simultaneous solution, Gaitan's estimators and the
    Monte Carlo those of the baseline reduction they decompose or repeat."""
    if labelled is None or not labelled.results:
        return [], ()
    samples, fits, results = seg.samples, seg.labelled_fits, list(labelled.results)
    dataset, unit, g, u_g = ds.name, ds.meta.output_unit, ds.meta.g_local, ds.meta.g_local_uncertainty
    chosen_rates = seg.labelled_rates if chosen_fits is seg.labelled_fits else rate_segments(chosen_fits)
    consistency = consistency_frame(chosen_fits, g, dataset, unit, chosen.model, chosen_rates)
    response = frequency_response_frame([r for r in chosen.results if r.rate_hz in labelled.rates], chosen_fits,
                                        dataset, unit, chosen.model, chosen_rates)
    both = [r for r in (simultaneous(samples, fits, g, u_g, config.fit.sine_fit == "four_parameter", seg.sums) if seg.streamed is None
                        else simultaneous_from_sums(seg.streamed.sums, fits, g, u_g)) if isinstance(r, IntrinsicResult)]
    outputs: list[Table | Figure] = [
        Table("uncertainty_budget", budget_frame(results, dataset, unit)),
        Table("simultaneous", simultaneous_frame(both, results, dataset, unit)),
        Table("consistency", consistency),
        Table("gaitan_estimators", gaitan_frame(fits, g, u_g, dataset, unit, seg.labelled_rates)),
        Table("frequency_response", response),
    ]
    if config.report.figures:
        def draw(out: Path) -> Path | None:
            from rotcal.report.plot import frequency_response_png  # matplotlib only when there is a plot to draw

            return frequency_response_png(response, out / "frequency_response.png", dataset)

        outputs.append(Figure("frequency_response_png", draw))
    notes = [n for n in [consistency_note(consistency)] if n]
    if config.uncertainty.monte_carlo:
        mc = monte_carlo_frame(monte_carlo(fits, g, u_g, config.uncertainty), results, dataset, unit)
        outputs.append(Table("monte_carlo", mc))
        notes.append(monte_carlo_note(mc))
    return outputs, tuple(notes)
