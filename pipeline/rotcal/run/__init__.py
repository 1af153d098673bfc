"""One dataset through every stage: ingest -> time base -> segment (labels,
then the signals for what labels leave out) -> fit -> combine (the
reductions) -> diagnose -> the recommended model -> metrology, and one
writer at the end that publishes what the stages produced as the output
directory. ``run_dataset`` is that straight sequence (drawn in
docs/architecture.md); the stage adapters are in ``stages`` (up to the
results) and ``recommended`` (what is made of them), the output items and
the writer in ``outputs``. The CLI and the batch runner both call
``run_dataset``; neither holds pipeline logic."""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from threadpoolctl import threadpool_limits

from rotcal.blockwise.load import load
from rotcal.combine import StaticReduction
from rotcal.config import RunConfig
from rotcal.errors import UndeterminedError
from rotcal.ingest.site import load_site, site_path
from rotcal.model.calibration import Recommended, mark_recommended
from rotcal.model.identification import Identification
from rotcal.model.outputs import INPUT_TABLES
from rotcal.model.results import Failure, IntrinsicResult, Table
from rotcal.report.publish import OutputDir
from rotcal.run.outputs import (
    calibration_document,
    calibration_output,
    certificate_outputs,
    diagnosis_outputs,
    noise_outputs,
    publish,
    result_tables,
)
from rotcal.run.recommended import (
    correction_stage,
    diagnose_stage,
    intrinsic_table,
    metrology_stage,
    recommend_stage,
    recommended_fits,
)
from rotcal.run.stages import Reductions, Segmented, determined, reduce, segment_and_fit

if TYPE_CHECKING:
    from rotcal.diagnose import Diagnosis
    from rotcal.diagnose.static import StaticDiagnosis


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
    diagnosis: Diagnosis | StaticDiagnosis | None = None
    static: StaticReduction | None = None


def run_dataset(path: Path, out: Path | OutputDir, meta_path: Path | None = None, config: RunConfig = RunConfig(),
                known: Mapping[tuple[int, ...], str] | None = None) -> RunOutcome:
    """Run the pipeline on one dataset (see ``_run``) with BLAS on one thread:
    rotcal's parallelism is across segments and datasets, and a threaded BLAS
    on small matrices competing with it costs more than it gives. A bare
    path ``out`` replaces only what a rotcal listing there names. ``known``:
    the inputs' SHA-256s the caller has computed (``ingest.duplicates.content_hashes``)."""
    site = load_site(site_path(Path(path), config.report.site))  # the site file checked before any work
    with threadpool_limits(limits=1, user_api="blas"), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outcome = _run(Path(path), out if isinstance(out, OutputDir) else OutputDir(Path(out)), meta_path, config, known, site)
    return replace(outcome, notes=outcome.notes + library_notes(caught))


def library_notes(caught: list[warnings.WarningMessage]) -> tuple[str, ...]:
    """A library's warnings during a run (numpy's, matplotlib's) as rotcal's
    notes, each once, with where it arose: they would otherwise reach stderr
    and a batch's log without saying which step or dataset."""
    seen = dict.fromkeys(f"{w.category.__name__} in {Path(w.filename).name}:{w.lineno}: {w.message}" for w in caught
                         if issubclass(w.category, (RuntimeWarning, UserWarning)))  # not a user's: resources, deprecations
    return tuple(f"a library warned (the result stands; tell the maintainers if it recurs): {text}" for text in seen)


def _run(path: Path, out: OutputDir, meta_path: Path | None, config: RunConfig,
         known: Mapping[tuple[int, ...], str] | None, site: Identification) -> RunOutcome:
    """Run the pipeline on one dataset and publish its tables as ``out``.

    Raises ``InputError`` for unreadable input and ``UndeterminedError`` when
    what remains after failed segments cannot determine any rate's result
    (the tables that describe the input, with the failure rows, are written then).
    """
    ds = load(path, meta_path, config)  # its samples streamed past [run] stream_above_samples (``streamed``)
    seg = segment_and_fit(ds, config)
    reductions = reduce(seg, ds)
    try:
        results, frames, warnings = determined(reductions, seg, path)
    except UndeterminedError:
        publish([t for t in _tables(seg, reductions) if t.name in INPUT_TABLES], out)
        raise
    assert isinstance(reductions, Reductions)  # determined() raises for a Failure
    diagnosis, diagnosis_notes = diagnose_stage(seg, reductions, results, ds, config)
    intrinsic = intrinsic_table(results, diagnosis, ds, reductions.static)
    chosen = recommend_stage(intrinsic, results, frames, diagnosis, reductions, config, diagnosis_notes)
    # the model-dependent tables of the recommended model
    metrology, metrology_notes = metrology_stage(seg, reductions.labelled, chosen,
                                                 recommended_fits(seg, diagnosis, chosen, ds, config), ds, config)
    corrections, correction_warnings = correction_stage(seg, reductions.static, ds)
    calibration = calibration_document(chosen, ds, config, known, site)
    noise, calibration, noise_notes = noise_outputs(seg, ds, config, calibration)
    outputs = [*noise, *_tables(seg, reductions), *result_tables(mark_recommended(intrinsic, chosen.model), chosen, ds),
               *diagnosis_outputs(diagnosis, seg.fits, results, ds, config), *corrections, *metrology,
               calibration_output(calibration), *certificate_outputs(config, calibration)]
    return RunOutcome(ds.name, ds.meta.output_unit, results, warnings + correction_warnings,
                      seg.notes + (reductions.static.notes if reductions.static else ()) + diagnosis_notes + metrology_notes
                      + noise_notes,
                      publish(outputs, out), chosen, diagnosis, reductions.static)


def _tables(seg: Segmented, reductions: Reductions | Failure) -> list[Table]:
    """The tables of the segmentation and of every reduction."""
    return [*seg.tables, *(t for r in ([] if isinstance(reductions, Failure) else reductions.all) for t in r.tables)]
