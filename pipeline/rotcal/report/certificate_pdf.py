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
(system fonts ignored) and the document carries no date: the same
certificate gives the same bytes on any machine."""

from __future__ import annotations

import json
import tempfile
from importlib.resources import files
from pathlib import Path

from rotcal.report.certificate_blocks import Document, Figure

TEMPLATE = "certificate.typ"
PAPERS = {"a4": "a4", "letter": "us-letter"}


def pdf_bytes(doc: Document, paper: str = "a4") -> bytes:
    """The PDF of ``doc`` on ``paper`` (a4 or letter)."""
    import typst

    with tempfile.TemporaryDirectory(prefix="rotcal-certificate-") as scratch:
        root = Path(scratch)
        names: dict[int, str] = {}

        def figure_name(figure: Figure) -> str:
            name = names.setdefault(id(figure), f"figure-{len(names) + 1}.png")
            (root / name).write_bytes(figure.png)
            return name

        data = {**doc.as_data(figure_name), "paper": PAPERS[paper]}
        (root / "data.json").write_text(json.dumps(data, ensure_ascii=False), encoding="utf-8")
        main = root / TEMPLATE
        main.write_text(files("rotcal.report").joinpath(TEMPLATE).read_text(encoding="utf-8"), encoding="utf-8")
        pdf = typst.compile(str(main), root=str(root), ignore_system_fonts=True)
    assert isinstance(pdf, bytes)
    return pdf
