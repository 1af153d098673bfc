"""The certificate as a PDF, typeset by Typst (the ``typst`` wheel: the
compiler and its fonts in one package, no system package, no TeX): the
layout is ``certificate.typ``, the content the certificate's blocks as
JSON, so that no text a laboratory gives is read as markup. Every page
carries the laboratory, the certificate number and "page x of y"; the
annex prints whole what the HTML folds away. Typst rather than reportlab:
its embedded fonts cover the certificate's Greek and symbols (ν, φ, ±, →,
ΔBIC) where reportlab's built-in fonts are Latin-1 only, its tables break
across pages with their header repeated, and the total page count is one
expression rather than a second pass. The fonts are the wheel's own
(system fonts ignored) and the document's date is the run's: the same
certificate gives the same bytes on any machine. Written as PDF/A-2b
(ISO 19005-2), the archival form a laboratory keeps its records in."""

from __future__ import annotations

import json
import tempfile
from importlib.resources import files
from pathlib import Path
from typing import Literal

from rotcal.report.certificate_blocks import Document, Figure

TEMPLATE = "certificate.typ"
PAPERS = {"a4": "a4", "letter": "us-letter"}
PDF_STANDARD: Literal["a-2b"] = "a-2b"  # PDF/A-2b (ISO 19005-2), for archiving: fonts embedded, colours defined, a document date


def pdf_bytes(doc: Document, paper: str = "a4") -> bytes:
    """The PDF of ``doc`` on ``paper`` (a4 or letter)."""
    import typst

    # a scratch folder of the files the template reads, removed file by file (what was written is known)
    root = Path(tempfile.mkdtemp(prefix="rotcal-certificate-"))
    written: list[Path] = []
    try:
        def figure_name(figure: Figure) -> str:
            name = f"figure-{len(written) + 1}.png"
            written.append(root / name)
            written[-1].write_bytes(figure.png)
            return name

        data = {**doc.as_data(figure_name), "paper": PAPERS[paper]}
        for name, text in (("data.json", json.dumps(data, ensure_ascii=False)),
                           (TEMPLATE, files("rotcal.report").joinpath(TEMPLATE).read_text(encoding="utf-8"))):
            written.append(root / name)
            written[-1].write_text(text, encoding="utf-8")
        pdf = typst.compile(str(root / TEMPLATE), root=str(root), ignore_system_fonts=True,
                            pdf_standards=PDF_STANDARD if doc.created_utc else None)
    finally:
        for path in written:
            path.unlink(missing_ok=True)
        root.rmdir()
    assert isinstance(pdf, bytes)
    return pdf
