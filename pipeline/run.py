"""One dataset through every stage: ingest -> time base -> segment (labels,
then the signals for what labels leave out) -> fit -> combine (the
reductions) -> metrology -> diagnose, and one writer at the end that
publishes the tables the stages produced into the output directory. The CLI
and the batch runner both call ``run_dataset``; neither holds pipeline
logic."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import polars as pl
from threadpoolctl import threadpool_limits

from rotcal.combine import (
    StaticReduction,
    intrinsic_frame,
    reduce_dwells,
    reduce_labelled,
    reduce_phase_free,
    reduce_static,
    summary_poses,
    table_step_poses,
)
from rotcal.config import RunConfig
from rotcal.errors import UndeterminedError
from rotcal.fit import fit_segments, fits_frame
from rotcal.ingest import Dataset, load_dataset
from rotcal.ingest.duplicates import content_hashes, duplicate_findings
from rotcal.metrology import (
    budget_frame,
    consistency_frame,
    consistency_note,
    correction_frame,
    correction_uncertainty_frame,
    corrections_from_poses,
    cross_sensitivity_frame,
    frequency_response_frame,
    gaitan_frame,
    monte_carlo,
    monte_carlo_frame,
    monte_carlo_note,
    simultaneous,
    simultaneous_frame,
    temperature_frame,
)
from rotcal.model import Failure, IntrinsicResult, Reduction, Table
from rotcal.model.calibration import BASELINE, REFINED, Recommended, mark_recommended, recommend, recommended_calibration
from rotcal.report.publish import OutputDir, publish_directory
from rotcal.segment import infer_segments, segment_by_labels
from rotcal.tables import write_parquet
from rotcal.timebase import classify_gaps, findings_frame, repair_timebase

if TYPE_CHECKING:
    from rotcal.diagnose import Diagnosis


@dataclass(frozen=True, eq=False)
class RunOutcome:
    """What a run produced: results per rate, warnings (failed segments or
    rates), notes (defaults applied), the files written and the recommended model."""

    dataset: str
    output_unit: str
    results: tuple[IntrinsicResult, ...]
    warnings: tuple[str, ...]
    notes: tuple[str, ...]
    written: tuple[Path, ...]
    recommended: Recommended
    diagnosis: Diagnosis | None = None
    static: StaticReduction | None = None


@dataclass(frozen=True, eq=False)
class Figure:
    """A file drawn into the output directory (a plot, the diagnosis
    report, calibration.json): ``draw`` returns its path, or None when there is nothing to draw."""

    name: str
    draw: Callable[[Path], Path | None]


# the run's files in the order they are published (and listed in RunOutcome.written)
PUBLISH_ORDER = ("segments", "fits", "timebase", "dwells", "diagnosis", "effect_parameters", "diagnosis_report",
                 "calibration", "intrinsic", "components", "cross_sensitivity", "correction", "correction_uncertainty",
                 "correction_temperature", "uncertainty_budget", "simultaneous", "consistency", "gaitan_estimators",
                 "frequency_response", "frequency_response_png", "monte_carlo", "poses", "certificate")
# the tables that describe the input rather than a result: published even when no rate can be determined
INPUT_TABLES = ("segments", "fits", "timebase", "dwells", "poses")


@dataclass(frozen=True, eq=False)
class Segmented:
    """A recording after the time base, segmentation and fit stages: its
    samples and segments (the inferred ones added when it is a ``table``
    recording), the segment fits, the segments fitted against their own
    phase, the dwells, the tables and what to tell the user."""

    samples: pl.DataFrame
    segments: pl.DataFrame
    fits: pl.DataFrame
    own_phase: frozenset[int]
    dwells: pl.DataFrame
    table: bool
    tables: tuple[Table, ...]
    warnings: tuple[str, ...]
    notes: tuple[str, ...]

    @property
    def labelled_fits(self) -> pl.DataFrame:
        """The fits of the segments whose phase is the table angle."""
        return self.fits.filter(~pl.col("segment").is_in(list(self.own_phase)))


@dataclass(frozen=True, eq=False)
class Reductions:
    """The reductions of a recording: a table recording's labelled one and
    those of its segments without an angle reference (which answer for
    their rates instead of the labelled one), or a static recording's."""

    labelled: Reduction | None
    unreferenced: tuple[Reduction, ...]
    static: StaticReduction | None

    @property
    def all(self) -> tuple[Reduction, ...]:
        return tuple(r for r in (self.labelled, *self.unreferenced, self.static) if r is not None)

    @property
    def unreferenced_rates(self) -> frozenset[float]:
        return frozenset(rate for r in self.unreferenced for rate in r.rates)

    def framed(self) -> list[tuple[IntrinsicResult, str]]:
        """Every result with the frame of its responsivity vectors, rates ordered by magnitude."""
        return sorted(((res, r.frame) for r in self.all for res in r.results), key=lambda p: _rate_order(p[0].rate_hz))

    def failures(self) -> list[Failure]:
        return sorted((f for r in self.all for f in r.failures), key=lambda f: _rate_order(f.rate_hz))


def _rate_order(rate_hz: float) -> tuple[float, float]:
    return abs(rate_hz), rate_hz


def run_dataset(path: Path, out: Path | OutputDir, meta_path: Path | None = None, config: RunConfig = RunConfig()) -> RunOutcome:
    """Run the pipeline on one dataset (see ``_run``) with BLAS on one thread:
    rotcal's parallelism is across segments and datasets, and a threaded BLAS
    on small matrices competing with it costs more than it gives. A bare
    path ``out`` replaces only what a rotcal listing there names."""
    with threadpool_limits(limits=1, user_api="blas"):
        return _run(Path(path), out if isinstance(out, OutputDir) else OutputDir(Path(out)), meta_path, config)


def _run(path: Path, out: OutputDir, meta_path: Path | None, config: RunConfig) -> RunOutcome:
    """Run the pipeline on one dataset and publish its tables as ``out``.

    Raises ``InputError`` for unreadable input and ``UndeterminedError`` when
    what remains after failed segments cannot determine any rate's result
    (the tables that describe the input, with the failure rows, are written then).
    """
    ds = load_dataset(path, meta_path, config.limits, config.run.workers)
    seg = segment_and_fit(ds, config)
    reductions = reduce(seg, ds)
    try:
        results, frames, warnings = determined(reductions, seg, path)
    except UndeterminedError:
        publish([t for t in _tables(seg, reductions) if t.name in INPUT_TABLES], out)
        raise
    assert isinstance(reductions, Reductions)  # determined() raises for a Failure
    diagnosis, diagnosis_notes = diagnose_stage(seg, reductions, results, ds, config)
    static = reductions.static
    intrinsic = intrinsic_table(results, diagnosis, ds, static)
    chosen = recommend(intrinsic, results, frames,
                       {REFINED: diagnosis.refined if diagnosis else (), **{n: (r,) for n, r in (static.nested if static else ())}},
                       tuple(diagnosis.before) if diagnosis else (),  # the modelled findings
                       baseline_reason(diagnosis, reductions, config, diagnosis_notes),
                       static.chosen if static and static.method == "orientation-free" else None)
    # the model-dependent tables of the recommended model
    metrology, metrology_notes = metrology_stage(seg, reductions.labelled, chosen,
                                                 recommended_fits(seg, diagnosis, chosen, ds, config), ds, config)
    corrections, correction_warnings = correction_stage(seg, reductions.static, ds)
    outputs = [*_tables(seg, reductions), *result_tables(mark_recommended(intrinsic, chosen.model), chosen, ds),
               *diagnosis_outputs(diagnosis, seg.fits, results, ds, config), *corrections, *metrology,
               calibration_output(chosen, ds, config), certificate_output(config)]
    return RunOutcome(ds.name, ds.meta.output_unit, results, warnings + correction_warnings,
                      seg.notes + (reductions.static.notes if reductions.static else ()) + diagnosis_notes + metrology_notes,
                      publish(outputs, out), chosen, diagnosis, reductions.static)


def _tables(seg: Segmented, reductions: Reductions | Failure) -> list[Table]:
    """The tables of the segmentation and of every reduction."""
    return [*seg.tables, *(t for r in ([] if isinstance(reductions, Failure) else reductions.all) for t in r.tables)]


def segment_and_fit(ds: Dataset, config: RunConfig) -> Segmented:
    """Time base, segments (labelled, then inferred from the signals) and
    the segment fits of a dataset."""
    timebase = repair_timebase(ds.samples, ds.name)
    samples, segments = segment_by_labels(timebase.samples, ds.name, ds.meta.angle_source)
    inferred = infer_segments(samples, segments, ds.name, ds.meta.plan_rates_hz, timebase.unrepairable)
    timebase = classify_gaps(timebase, inferred.samples, inferred.segments)  # gaps between segments: pauses
    # a table recording (labelled or found in the signals); otherwise a static one (``reduce``)
    table = not inferred.segments.filter(pl.col("kind").is_in(["static", "rotation"])).is_empty()
    if table:
        samples, segments = inferred.samples, inferred.segments
    referenced = segments.filter(pl.col("angle_source") != "none")
    fits = fits_frame(fit_segments(samples, referenced, config.fit, config.run.workers)
                      + (list(inferred.fits) if table else []), segments, ds.name)
    findings = pl.concat([findings_frame(duplicate_findings(ds.name, ds.copies)), timebase.findings,
                          findings_frame(list(inferred.findings) if table else [])])
    return Segmented(samples, segments, fits, inferred.own_phase if table else frozenset(), inferred.dwells, table,
                     (Table("segments", segments), Table("fits", fits), Table("timebase", findings)),
                     tuple(timebase.warnings) + (inferred.warnings if table else ()),
                     ds.notes + (inferred.notes if table else ()))


def reduce(seg: Segmented, ds: Dataset) -> Reductions | Failure:
    """The reductions of a recording. A table recording: its labelled
    segments (``combine.labelled``), and those without an angle reference
    (``combine.unreferenced``: rotations fitted against their own phase, and
    the dwells when no labelled static sequence gives the static result). A
    static recording: its poses (``combine.static``), or why they cannot be
    reduced."""
    g, u = ds.meta.g_local, ds.meta.g_local_uncertainty
    if not seg.table:
        summaries = None if ds.summaries is None else summary_poses(ds.summaries)
        static = reduce_static(seg.samples, seg.segments, ds.name, g, u, summaries)
        return static if isinstance(static, Failure) else Reductions(None, (), static)
    labelled = reduce_labelled(seg.labelled_fits, g, u, ds.name)
    phase_free = reduce_phase_free(seg.fits, seg.own_phase, g, u)
    dwells = reduce_dwells(seg.dwells, not any(r.rate_hz == 0 for r in labelled.results), g, u)
    return Reductions(labelled.without(phase_free.rates | dwells.rates), (phase_free, dwells), None)


def determined(reductions: Reductions | Failure, seg: Segmented, path: Path
               ) -> tuple[tuple[IntrinsicResult, ...], tuple[str, ...], tuple[str, ...]]:
    """The results (rates ordered by magnitude), the frames of their
    responsivity vectors and the warnings: failed segments and rates.
    Raises ``UndeterminedError`` when no rate is determined."""
    refused = "no table segments, and the static poses cannot be reduced"
    if isinstance(reductions, Failure):
        raise UndeterminedError(f"{refused}: {reductions.reason}", path=path)
    if reductions.static is not None and not reductions.static.results:  # a refusal, with its pose table
        raise UndeterminedError(f"{refused}: {reductions.static.failures[0].reason}", path=path)
    failed = seg.fits.filter(seg.fits["status"] == "failed").unique("segment", keep="first", maintain_order=True)
    warnings = (seg.warnings + tuple(w for r in reductions.all for w in r.warnings)
                + tuple(f"segment {s} ({a}, {r:g} Hz): {why}"
                        for s, a, r, why in failed.select("segment", "axis", "rate_hz", "reason").iter_rows())
                + tuple(f"rate {f.rate_hz:g} Hz not determined: {f.reason}" for f in reductions.failures()))
    framed = reductions.framed()
    if not framed:
        if not warnings:
            raise UndeterminedError("no static or rotation segments: the samples carry no axis and rate labels", path=path)
        more = f" (and {len(warnings) - 1} more problems)" if len(warnings) > 1 else ""
        raise UndeterminedError(f"no rate can be determined: {warnings[0]}{more}", path=path)
    return tuple(r for r, _ in framed), tuple(f for _, f in framed), warnings


def diagnose_stage(seg: Segmented, reductions: Reductions, results: tuple[IntrinsicResult, ...], ds: Dataset,
                   config: RunConfig) -> tuple[Diagnosis | None, tuple[str, ...]]:
    """The diagnosis of a table recording whose segments all have the table
    angle (its models need it), with its notes."""
    if reductions.unreferenced_rates:
        return None, ("diagnosis skipped: segments without a table angle (its models need the angle)",)
    if not config.diagnosis.enabled or reductions.static is not None:
        return None, ()
    from rotcal.diagnose import diagnose  # scipy.stats loads when diagnosing, after the large stages

    diagnosis = diagnose(seg.samples, seg.segments, seg.fits, results, ds.name, ds.meta.output_unit,
                         ds.meta.g_local_uncertainty, ds.meta.angle_source == "measured", config.diagnosis)
    if diagnosis is not None and diagnosis.final.obs.n < diagnosis.samples_available:
        return diagnosis, (f"diagnosis modelled {diagnosis.final.obs.n:,} of the {diagnosis.samples_available:,} "
                           f"samples (long segments thinned evenly; [diagnosis] max_samples)",)
    return diagnosis, ()


def intrinsic_table(results: tuple[IntrinsicResult, ...], diagnosis: Diagnosis | None, ds: Dataset,
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


def baseline_reason(diagnosis: Diagnosis | None, reductions: Reductions, config: RunConfig,
                    diagnosis_notes: tuple[str, ...]) -> str:
    """Why the baseline model is the result when it is: what the diagnosis found, or why it did not run."""
    if diagnosis is not None:
        return "the diagnosis found no effect to model"
    why = (diagnosis_notes[0] if diagnosis_notes else "static poses (the diagnosis models table rotations)"
           if reductions.static is not None else "switched off ([diagnosis] enabled = false)"
           if not config.diagnosis.enabled else "no fitted table segments")
    return f"diagnosis not run: {why.removeprefix('diagnosis skipped: ')}"


def result_tables(intrinsic: pl.DataFrame, chosen: Recommended, ds: Dataset) -> list[Table]:
    """The ``intrinsic`` table and the cross-sensitivities of the
    recommended model in each result's frame."""
    return [Table("intrinsic", intrinsic),
            Table("cross_sensitivity", cross_sensitivity_frame(list(zip(chosen.results, chosen.frames)), ds.name,
                                                               chosen.model, ds.meta.output_unit,
                                                               ds.meta.g_local_uncertainty))]


def calibration_output(chosen: Recommended, ds: Dataset, config: RunConfig) -> Figure:
    """``calibration.json``: the recommended result per rate, g_local and
    its source, the inputs' hashes and every configuration key."""
    calibration = recommended_calibration(chosen, ds.name, ds.meta, content_hashes(ds.inputs, ds.root), asdict(config))
    return Figure("calibration", lambda out: calibration.write(out / "calibration.json"))


def diagnosis_outputs(diagnosis: Diagnosis | None, fits: pl.DataFrame, results: tuple[IntrinsicResult, ...],
                      ds: Dataset, config: RunConfig) -> list[Table | Figure]:
    """The diagnosis's findings and effect parameters, and its report when wanted."""
    if diagnosis is None:
        return []
    outputs: list[Table | Figure] = [Table("diagnosis", diagnosis.findings),
                                     Table("effect_parameters", diagnosis.parameters)]
    if config.diagnosis.report:
        def draw(out: Path) -> Path:
            from rotcal.report.diagnosis import write_report  # matplotlib only when a report is wanted

            return write_report(diagnosis, fits, results, ds.name, ds.meta.output_unit, out, config.report.figures)

        outputs.append(Figure("diagnosis_report", draw))
    return outputs


def correction_stage(seg: Segmented, static: StaticReduction | None, ds: Dataset) -> tuple[list[Table], tuple[str, ...]]:
    """AN4399's correction tables from the static positions (a table
    recording's steps, or the static reduction's poses), with their warnings."""
    positions = table_step_poses(seg.samples, seg.segments) if static is None else static.positions
    corrections, warnings = corrections_from_poses(positions)
    if not corrections:
        return [], tuple(warnings)
    dataset, unit = ds.name, ds.meta.output_unit
    tables = [Table("correction", correction_frame(corrections, dataset, unit)),
              Table("correction_uncertainty", correction_uncertainty_frame(corrections, dataset, unit))]
    by_temperature = temperature_frame(corrections, dataset, unit)
    return tables + ([Table("correction_temperature", by_temperature)] if not by_temperature.is_empty() else []), tuple(warnings)


def recommended_fits(seg: Segmented, diagnosis: Diagnosis | None, chosen: Recommended, ds: Dataset,
                     config: RunConfig) -> pl.DataFrame:
    """The segment fits under the recommended model: under the refined one,
    those of the samples less its modelled effects (``diagnose.corrected``)."""
    if chosen.model == BASELINE or diagnosis is None:
        return seg.labelled_fits
    from rotcal.diagnose.corrected import without_effects

    samples = without_effects(seg.samples, seg.segments, seg.fits, diagnosis)
    referenced = seg.segments.filter(pl.col("angle_source") != "none")
    return fits_frame(fit_segments(samples, referenced, config.fit, config.run.workers), seg.segments, ds.name)


def metrology_stage(seg: Segmented, labelled: Reduction | None, chosen: Recommended, chosen_fits: pl.DataFrame,
                    ds: Dataset, config: RunConfig) -> tuple[list[Table | Figure], tuple[str, ...]]:
    """Issue 3's tables of a table (step or rotation) dataset: uncertainty
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
    consistency = consistency_frame(chosen_fits, g, dataset, unit, chosen.model)
    response = frequency_response_frame([r for r in chosen.results if r.rate_hz in labelled.rates], chosen_fits,
                                        dataset, unit, chosen.model)
    both = [r for r in simultaneous(samples, fits, g, u_g, config.fit.sine_fit == "four_parameter") if isinstance(r, IntrinsicResult)]
    outputs: list[Table | Figure] = [
        Table("uncertainty_budget", budget_frame(results, dataset, unit)),
        Table("simultaneous", simultaneous_frame(both, results, dataset, unit)),
        Table("consistency", consistency),
        Table("gaitan_estimators", gaitan_frame(fits, g, u_g, dataset, unit)),
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


def certificate_output(config: RunConfig) -> Figure:
    """The certificate (``report.certificate``), published last: a view of
    the files published before it, drawn when they include calibration.json."""
    def draw(out: Path) -> Path | None:
        if not (out / "calibration.json").is_file():
            return None
        from rotcal.report.certificate import write_certificate  # matplotlib only when there is a page to draw

        return write_certificate(out, config.report.figures)

    return Figure("certificate", draw)


def publish(outputs: Sequence[Table | Figure], out: OutputDir) -> tuple[Path, ...]:
    """Publish what the run produced as the whole of ``out``, in
    ``PUBLISH_ORDER`` (an item it does not name after those it does): each
    table as Parquet under its schema (``tables.write_parquet``), each
    figure drawn, staged beside ``out``, listed and swapped in
    (``report.publish``); the paths published."""
    def write(staging: Path) -> list[Path]:
        order = {name: k for k, name in enumerate(PUBLISH_ORDER)}
        items = sorted(outputs, key=lambda o: order.get(o.name, len(order)))
        paths = (write_parquet(i.data, staging / f"{i.name}.parquet", i.name) if isinstance(i, Table) else i.draw(staging)
                 for i in items)
        return [path for path in paths if path is not None]

    return publish_directory(out, write)
