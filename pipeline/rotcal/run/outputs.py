"""What a run publishes: its output items (``Table``s and ``Figure``s: the
intrinsic and cross-sensitivity tables of the recommended model,
calibration.json, the diagnosis's tables and report, the certificate) and
the one writer, ``publish``, in the order of the outputs registry
(``model.outputs.OUTPUTS``), which names every item."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import polars as pl

from rotcal.config import RunConfig
from rotcal.ingest.dataset import Dataset
from rotcal.ingest.duplicates import content_hashes
from rotcal.metrology import (
    cross_sensitivity_frame,
)
from rotcal.model.calibration import Calibration, Recommended, recommended_calibration
from rotcal.model.identification import Identification
from rotcal.model.outputs import output, publish_rank
from rotcal.model.results import IntrinsicResult, Table
from rotcal.report.publish import OutputDir, publish_directory
from rotcal.tables import contract_table, write_table

if TYPE_CHECKING:
    import pyarrow as pa

    from rotcal.diagnose import Diagnosis
    from rotcal.diagnose.static import StaticDiagnosis
    from rotcal.report.certificate_blocks import Document
    from rotcal.run.stages import Segmented


@dataclass(frozen=True, eq=False)
class Figure:
    """A file drawn into the output directory (a plot, the diagnosis
    report, calibration.json): ``draw`` returns its path, or None when there is nothing to draw."""

    name: str
    draw: Callable[[Path], Path | None]

    def __post_init__(self) -> None:
        if output(self.name).is_table:
            raise KeyError(f"{self.name!r} is a table, published as a Table")


def result_tables(intrinsic: pl.DataFrame, chosen: Recommended, ds: Dataset) -> list[Table]:
    """The ``intrinsic`` table and the cross-sensitivities of the
    recommended model in each result's frame."""
    return [Table("intrinsic", intrinsic),
            Table("cross_sensitivity", cross_sensitivity_frame(list(zip(chosen.results, chosen.frames)), ds.name,
                                                               chosen.model, ds.meta.output_unit,
                                                               ds.meta.g_local_uncertainty))]


def calibration_document(chosen: Recommended, ds: Dataset, config: RunConfig,
                         known: Mapping[tuple[int, ...], str] | None = None,
                         site: Identification = Identification()) -> Calibration:
    """The run's ``calibration.json``: the recommended result per rate,
    g_local and its source, the inputs' hashes (those ``known`` not read
    again: ``content_hashes``), every configuration key and the
    certificate's fields (``dataset.toml``'s over the ``site`` file's)."""
    return recommended_calibration(chosen, ds.name, ds.meta, content_hashes(ds.inputs, ds.root, known), asdict(config),
                                   site)


def calibration_output(calibration: Calibration) -> Figure:
    """``calibration.json`` written (and validated: ``Calibration.write``)."""
    return Figure("calibration", lambda out: calibration.write(out / "calibration.json"))


def diagnosis_outputs(diagnosis: Diagnosis | StaticDiagnosis | None, fits: pl.DataFrame, results: tuple[IntrinsicResult, ...],
                      ds: Dataset, config: RunConfig) -> list[Table | Figure]:
    """The diagnosis's findings and effect parameters, and its report when wanted."""
    if diagnosis is None:
        return []
    outputs: list[Table | Figure] = [Table("diagnosis", diagnosis.findings),
                                     Table("effect_parameters", diagnosis.parameters)]
    if config.diagnosis.report:
        def draw(out: Path) -> Path:
            from rotcal.diagnose.static import StaticDiagnosis
            from rotcal.report.diagnosis import write_report  # the report modules only when a report is wanted
            from rotcal.report.static_diagnosis import write_static_report

            if isinstance(diagnosis, StaticDiagnosis):
                return write_static_report(diagnosis, results, ds.name, ds.meta.output_unit, out, config.report.figures)
            return write_report(diagnosis, fits, results, ds.name, ds.meta.output_unit, out, config.report.figures)

        outputs.append(Figure("diagnosis_report", draw))
    return outputs


def noise_outputs(seg: Segmented, ds: Dataset, config: RunConfig,
                  calibration: Calibration) -> tuple[list[Table | Figure], Calibration, tuple[str, ...]]:
    """The ``noise`` table, the Allan-deviation figure (``noise_allan.png``,
    with figures) and ``calibration`` with the noise model (of a capture
    read block by block, from the residual pieces its fit pass pooled)."""
    from rotcal.noise import calibration_noise, noise_frame

    model = seg.noise_model(ds.meta.output_unit)
    outputs: list[Table | Figure] = [Table("noise", noise_frame(model, ds.name))]
    if config.report.figures:
        def draw(out: Path) -> Path | None:
            from rotcal.report.noise_figure import allan_png

            return allan_png(model, out / "noise_allan.png", f"{ds.name}: Allan deviation of the residuals and the noise model")

        outputs.append(Figure("noise_allan_png", draw))
    return outputs, replace(calibration, noise=calibration_noise(model)), offset_notes(seg.fits)


def offset_notes(fits: pl.DataFrame) -> tuple[str, ...]:
    """The run's notes on the offsets' noise (``fit.wander``): where the
    noise model could not be identified, or the wander is slower than the record."""
    from rotcal.fit.wander import NOT_MODELLED, SLOWER_THAN_RECORD

    noted = fits.filter(pl.col("noise_note").is_in([NOT_MODELLED, SLOWER_THAN_RECORD]))["noise_note"]
    return tuple(f"segment offsets: {note}" for note in dict.fromkeys(noted.to_list()))


@dataclass(frozen=True, eq=False)
class View:
    """A file drawn from what was published before it (the certificate):
    ``draw`` gets the output directory and the tables published there, by
    name, as written; it returns its path, or None when there is nothing to draw."""

    name: str
    draw: Callable[[Path, Mapping[str, pa.Table]], Path | None]

    def __post_init__(self) -> None:
        if output(self.name).is_table:
            raise KeyError(f"{self.name!r} is a table, published as a Table")


def certificate_outputs(config: RunConfig, calibration: Calibration) -> list[View]:
    """The certificate (``report.certificate``), published last: a view of
    the files published before it, drawn when they include calibration.json,
    as HTML and (``[report] pdf``) as PDF, both from one document."""
    built: dict[str, Document] = {}

    def document(out: Path, published: Mapping[str, pa.Table]) -> Document | None:
        if not (out / "calibration.json").is_file():
            return None
        if "doc" not in built:
            from rotcal.report.certificate import document as certificate_document

            # calibration_output wrote and validated this document in this same
            # publish, and the tables are those just written: neither is read back
            built["doc"] = certificate_document(out, config.report.figures, calibration=calibration, published=published)
        return built["doc"]

    def html(out: Path, published: Mapping[str, pa.Table]) -> Path | None:
        from rotcal.report.certificate import write_certificate

        doc = document(out, published)
        return None if doc is None else write_certificate(out, doc=doc)

    def pdf(out: Path, published: Mapping[str, pa.Table]) -> Path | None:
        from rotcal.report.certificate import write_certificate_pdf

        doc = document(out, published)
        return None if doc is None or not config.report.pdf else write_certificate_pdf(out, config.report.paper, doc=doc)

    return [View("certificate", html), View("certificate_pdf", pdf)]


def publish(outputs: Sequence[Table | Figure | View], out: OutputDir) -> tuple[Path, ...]:
    """Publish what the run produced as the whole of ``out``, in the
    registry's order (``model.outputs.OUTPUTS``, which names every item): each
    table as Parquet under its schema (``tables.contract_table``; handed to
    ``out.on_table`` too), each figure drawn, each view drawn from the
    tables before it, staged beside ``out``, listed and swapped in
    (``report.publish``); the paths published."""
    published: dict[str, pa.Table] = {}

    def write(staging: Path) -> list[Path]:
        paths = (write_item(i, staging) for i in sorted(outputs, key=lambda o: publish_rank(o.name)))
        return [path for path in paths if path is not None]

    def write_item(item: Table | Figure | View, staging: Path) -> Path | None:
        if isinstance(item, Figure):
            return item.draw(staging)
        if isinstance(item, View):
            return item.draw(staging, published)
        table = published[item.name] = contract_table(item.data, item.name)
        if out.on_table is not None:
            out.on_table(item.name, table)
        return write_table(table, staging / f"{item.name}.parquet")

    return publish_directory(out, write)
