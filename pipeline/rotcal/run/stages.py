"""The run's stage adapters up to the results: each calls one stage package
on what the stages before it produced and returns what the next reads (a
recording's ``Segmented`` samples, segments and fits; its ``Reductions``;
its results per rate). What is made of the results (the diagnosis, the
recommended model and its tables) is in ``recommended``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path

import polars as pl

from rotcal.blockwise.load import StreamedDataset, streamed_segments
from rotcal.blockwise.segments import StreamedSegments
from rotcal.combine import (
    StaticReduction,
    reduce_dwells,
    reduce_labelled,
    reduce_phase_free,
    reduce_static,
    summary_poses,
)
from rotcal.combine.labelled import RateSegments, rate_segments
from rotcal.config import RunConfig
from rotcal.errors import UndeterminedError
from rotcal.fit import OffsetCovariance, SegmentFit, fit_segments, fits_frame
from rotcal.fit.normal import SineSums
from rotcal.ingest.dataset import Dataset
from rotcal.ingest.duplicates import duplicate_findings
from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table
from rotcal.noise import NoiseModel
from rotcal.segment import infer_segments, segment_by_labels
from rotcal.segment.angles import check_angle_rates, partial_angles
from rotcal.timebase import classify_gaps, findings_frame, repair_timebase


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
    streamed: StreamedSegments | None = None  # a capture read block by block: ``samples`` holds only what ``_from_stream`` keeps
    clock_factor: float = 1.0  # what the fitted rates were multiplied by to be on the table's clock (``Inference``)
    sums: Mapping[int, SineSums] = field(default_factory=dict)  # the three-parameter fits' sums by segment (in memory)
    unused: pl.DataFrame | None = None  # still intervals the detector rejected (``still_unused`` rows; a table recording's)
    offsets: OffsetCovariance | None = None  # the offsets' covariance the segments showed (``fit.wander``), for the dwells

    @cached_property
    def labelled_fits(self) -> pl.DataFrame:
        """The fits of the segments whose phase is the table angle (one frame, read by several stages)."""
        return self.fits.filter(~pl.col("segment").is_in(list(self.own_phase)))

    @cached_property
    def labelled_rates(self) -> RateSegments:
        """``combine.rate_segments`` of ``labelled_fits``, for the reduction and the metrology that read them."""
        return rate_segments(self.labelled_fits)

    def noise_model(self, output_unit: str) -> NoiseModel:
        """Each channel's noise model from the residuals of the fitted model
        (``noise.identify_noise``; of a capture read block by block, from the
        pieces its fit pass pooled), identified once for the diagnosis and
        the noise outputs that both read it."""
        key = f"_noise_model_{output_unit}"
        if key not in self.__dict__:  # frozen: cached as cached_property caches, in the instance's dict
            from rotcal.noise import identify_noise

            self.__dict__[key] = identify_noise(self.samples, self.segments, self.fits, self.dwells, output_unit,
                                                None if self.streamed is None else self.streamed.noise_pooled())
        model: NoiseModel = self.__dict__[key]
        return model


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


def segment_and_fit(ds: Dataset, config: RunConfig) -> Segmented:
    """Time base, segments (labelled, then inferred from the signals) and
    the segment fits of a dataset; of a streamed one (``blockwise.load``) block
    by block, or in memory with a note where the streamed path cannot take it."""
    if isinstance(ds, StreamedDataset):
        streamed, notes = streamed_segments(ds, config)
        if streamed is not None:
            return _from_stream(ds, streamed)
        assert ds.in_memory is not None
        whole = ds.in_memory()
        ds = replace(whole, notes=whole.notes + notes)
    timebase = repair_timebase(ds.samples, ds.name)
    samples, segments = segment_by_labels(timebase.samples, ds.name, ds.meta.angle_source)
    check_angle_rates(samples, ds.root)  # labels against each other: a unit mistake is refused
    partial = partial_angles(samples, segments)
    inferred = infer_segments(samples, segments, ds.name, ds.meta.plan_rates_hz, timebase.unrepairable)
    timebase = classify_gaps(timebase, inferred.samples, inferred.segments)  # gaps between segments: pauses
    # a table recording (labelled or found in the signals); otherwise a static one (``reduce``)
    table = not inferred.segments.filter(pl.col("kind").is_in(["static", "rotation"])).is_empty()
    if table:
        samples, segments = inferred.samples, inferred.segments
    # the segments fitted against the table angle, and those fitted against their own phase (``infer_segments``)
    # joining them in the noise's spectrum and the offsets' wander, which all segments together measure
    own = {f.segment: f for f in inferred.fits if f.status == "ok"} if table else {}
    fitted = fit_segments(samples, segments.filter((pl.col("angle_source") != "none") | pl.col("segment").is_in(list(own))),
                          config.fit, config.run.workers, own, inferred.clock_factor)
    own_fitted = {f.segment: f for f in fitted if f.segment in own}
    fits = fits_frame([f for f in fitted if f.segment not in own]
                      + ([own_fitted.get(f.segment, f) for f in inferred.fits] if table else []), segments, ds.name)
    findings = pl.concat([findings_frame(duplicate_findings(ds.name, ds.copies)), timebase.findings,
                          findings_frame(list(inferred.findings) if table else [])])
    return Segmented(samples, segments, fits, inferred.own_phase if table else frozenset(), inferred.dwells, table,
                     (Table("segments", segments), Table("fits", fits), Table("timebase", findings)),
                     tuple(timebase.warnings) + partial + (inferred.warnings if table else ()),
                     ds.notes + (inferred.notes if table else _static_route(inferred.route)),
                     sums={f.segment: f.sums for f in fitted if f.sums is not None},
                     clock_factor=inferred.clock_factor if table else 1.0, unused=inferred.unused if table else None,
                     offsets=shared_offsets(fitted))


def shared_offsets(fits: list[SegmentFit]) -> OffsetCovariance | None:
    """The offsets' covariance the recording's segments showed (each ok fit holds the same), None where white."""
    return next((f.offsets for f in fits if f.offsets is not None), None)


def _static_route(evidence: str) -> tuple[str, ...]:
    """The static route's note: what the signals showed instead of a table's segments."""
    return (f"route: static poses, the signals showing no table segments ({evidence}); every still interval the detector "
            "accepts enters the static fit",) if evidence else ()


def _from_stream(ds: StreamedDataset, streamed: StreamedSegments) -> Segmented:
    """``segment_and_fit``'s result from a streamed capture's segments and
    fits; the samples kept are the capture's first and the static segments'
    (every sample is labelled: ``infer_segments`` adds no segment)."""
    assert ds.timebase is not None
    inferred = infer_segments(streamed.static_samples(), streamed.segments, ds.name, ds.meta.plan_rates_hz,
                              ds.timebase.unrepairable)
    fits = fits_frame(streamed.fits + list(inferred.fits), inferred.segments, ds.name)
    findings = pl.concat([findings_frame(duplicate_findings(ds.name, ds.copies)), ds.timebase.findings,
                          findings_frame(list(inferred.findings))])
    return Segmented(inferred.samples, inferred.segments, fits, inferred.own_phase, inferred.dwells, True,
                     (Table("segments", inferred.segments), Table("fits", fits), Table("timebase", findings)),
                     tuple(ds.timebase.warnings) + inferred.warnings, ds.notes + inferred.notes, streamed,
                     clock_factor=inferred.clock_factor, unused=inferred.unused, offsets=shared_offsets(streamed.fits))


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
        static = reduce_static(seg.samples, seg.segments, ds.name, g, u, summaries, ds.meta.placement)
        return static if isinstance(static, Failure) else Reductions(None, (), static)
    labelled = reduce_labelled(seg.labelled_fits, g, u, ds.name, seg.labelled_rates)
    phase_free = reduce_phase_free(seg.fits, seg.own_phase, g, u)
    single = frozenset(seg.segments.filter(pl.col("kind") == "pose")["segment"].to_list())
    dwells = reduce_dwells(seg.dwells, not any(r.rate_hz == 0 for r in labelled.results), g, u, single, seg.unused,
                           seg.samples, seg.offsets)
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
