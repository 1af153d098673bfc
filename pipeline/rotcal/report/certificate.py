"""The calibration certificate of one dataset, a view of a run's published
files (``certificate_content``): one self-contained HTML page
(``certificate.html``, figures embedded as data: URIs, no other resource)
and the PDF made from the same blocks (``certificate_pdf``). The HTML folds
the annex's long tables away; the PDF prints them whole."""

from __future__ import annotations

from collections.abc import Mapping
from functools import cache
from html import escape
from importlib.resources import files
from pathlib import Path
from string import Template
from typing import TYPE_CHECKING

import polars as pl

from rotcal.model.calibration import Calibration
from rotcal.model.identification import NOT_GIVEN
from rotcal.report.certificate_blocks import Block, Document, Fields, Figure, Grid, Heading, Section, Text
from rotcal.report.certificate_content import TABLES, certificate_document, read_tables
from rotcal.tables import atomic_write

if TYPE_CHECKING:
    import pyarrow as pa

CERTIFICATE = "certificate.html"
CERTIFICATE_PDF = "certificate.pdf"
__all__ = ["CERTIFICATE", "CERTIFICATE_PDF", "document", "read_tables", "render", "rewrite_certificates", "write_certificate",
           "write_certificate_pdf"]


def _cell(text: object, cls: str = "", tag: str = "td") -> str:
    return f'<{tag} class="{cls}">{escape(str(text))}</{tag}>' if cls else f"<{tag}>{escape(str(text))}</{tag}>"


def _grid(g: Grid) -> str:
    head = "".join(f"<th>{escape(h)}</th>" for h in g.header)
    rows = []
    for r, row in enumerate(g.rows):
        keys = "".join(f' data-{k}="{escape(v)}"' for k, v in (g.keys[r] if r < len(g.keys) else ()))
        cells = "".join(_cell(c, g.column_class(i), "th" if g.row_heads and i == 0 else "td") for i, c in enumerate(row))
        rows.append(f"<tr{keys}>{cells}</tr>")
    table = f"<table><thead><tr>{head}</tr></thead><tbody>{''.join(rows)}</tbody></table>"
    return table if g.folded is None else f"<details><summary>{escape(g.folded)}</summary>{table}</details>"


def _block(b: Block) -> str:
    if isinstance(b, Text):
        return f'<p class="note">{escape(b.text)}</p>' if b.note else f"<p>{escape(b.text)}</p>"
    if isinstance(b, Heading):
        return f"<h3>{escape(b.text)}</h3>"
    if isinstance(b, Fields):
        rows = "".join(f"<tr><th>{escape(k)}</th>{_cell(v, 'absent' if v == 'not given' else '')}</tr>" for k, v in b.pairs)
        return f'<table class="fields"><tbody>{rows}</tbody></table>'
    if isinstance(b, Grid):
        return _grid(b)
    if isinstance(b, Figure):
        from rotcal.report.certificate_figures import data_uri  # matplotlib only when a figure is embedded

        return f'<p><img alt="{escape(b.alt)}" src="{data_uri(b.png)}"></p>'
    text = f"<pre>{escape(b.text)}</pre>"
    return text if b.folded is None else f"<details><summary>{escape(b.folded)}</summary>{text}</details>"


def _section(s: Section) -> str:
    return f"<h2>{escape(s.title)}</h2>" + "".join(_block(b) for b in s.blocks)


def _approval(doc: Document) -> str:
    a = doc.approval
    statements = "".join(f"<p>{escape(s)}</p>" for s in doc.statements)
    return ("<h2>8. Approval</h2>" + statements + _block(Fields((
        ("approved by", a.name), ("function", a.function), ("date of issue", a.date_of_issue),
        ("signature", "")))))


@cache
def _page() -> Template:
    """The page's template (``certificate.html``), read once a process."""
    return Template(files("rotcal.report").joinpath(CERTIFICATE).read_text(encoding="utf-8"))


def html(doc: Document) -> str:
    """The page of ``doc``."""
    body = ("".join(_section(s) for s in doc.sections) + _approval(doc)
            + '<h2 class="annex">Annex: evidence and records</h2>' + "".join(_section(s) for s in doc.annex)
            + f'<p class="note end">End of certificate{"" if doc.number == NOT_GIVEN else " " + escape(doc.number)}</p>')
    return _page().substitute(title=escape(doc.title), number=escape(doc.number), laboratory=escape(doc.laboratory),
                              subtitle=escape(doc.subtitle), generated=escape(doc.generated), sections=body)


def document(run_dir: Path, figures: bool = True, calibration: Calibration | None = None,
             published: Mapping[str, pa.Table] | None = None) -> Document:
    """The certificate of the run in ``run_dir``; raises ``InputError``
    when it holds no readable ``calibration.json`` or an unreadable table.
    ``calibration``: the document the run itself has just written there
    (and validated), taken instead of reading it back. ``published``: the
    tables that run wrote into ``run_dir``, as it wrote them (by name),
    taken instead of reading the files back."""
    run_dir = Path(run_dir)
    cal = Calibration.read(run_dir / "calibration.json") if calibration is None else calibration
    tables = read_tables(run_dir) if published is None else {
        name: pl.DataFrame(published[name]) for name in TABLES if name in published}
    return certificate_document(run_dir, cal, tables, figures)


def render(run_dir: Path, figures: bool = True, calibration: Calibration | None = None,
           published: Mapping[str, pa.Table] | None = None) -> str:
    """The certificate page of the run in ``run_dir`` (``document``'s arguments)."""
    return html(document(run_dir, figures, calibration, published))


def write_certificate(run_dir: Path, figures: bool = True, calibration: Calibration | None = None,
                      published: Mapping[str, pa.Table] | None = None, doc: Document | None = None) -> Path:
    """Write ``certificate.html`` into ``run_dir`` (atomically) from its
    published files (``document``'s arguments), or of ``doc`` when given."""
    path = Path(run_dir) / CERTIFICATE
    text = html(doc or document(Path(run_dir), figures, calibration, published))
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_certificate_pdf(run_dir: Path, paper: str = "a4", figures: bool = True, calibration: Calibration | None = None,
                          published: Mapping[str, pa.Table] | None = None, doc: Document | None = None) -> Path:
    """Write ``certificate.pdf`` into ``run_dir`` (atomically), on ``paper`` (a4 or letter)."""
    from rotcal.report.certificate_pdf import pdf_bytes  # the typesetter only when a PDF is wanted

    data = pdf_bytes(doc or document(Path(run_dir), figures, calibration, published), paper)
    return atomic_write(Path(run_dir) / CERTIFICATE_PDF, lambda tmp: tmp.write_bytes(data))


def rewrite_certificates(run_dir: Path) -> list[Path]:
    """``rotcal certificate``: the run's certificate drawn again from its
    files, as HTML, and as PDF on its paper where the run wrote one (its
    configuration's ``[report] pdf``; a run from before the PDF lists none,
    and a file its listing does not name would bar the next run's output)."""
    run_dir = Path(run_dir)
    cal = Calibration.read(run_dir / "calibration.json")
    doc = document(run_dir, calibration=cal)
    written = [write_certificate(run_dir, doc=doc)]
    report = cal.configuration.get("report", {})
    if report.get("pdf") is True:
        written.append(write_certificate_pdf(run_dir, report.get("paper", "a4"), doc=doc))
    return written
