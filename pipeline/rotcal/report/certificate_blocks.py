"""The certificate as a document of plain blocks (text, fields, tables,
figures), drawn from a run's files once and rendered twice: as HTML
(``certificate``) and as PDF (``certificate_pdf``). The main part speaks
to the customer and names no file of the run; the annex holds the tables
and the evidence, printed whole (the HTML folds the long ones away)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

STATEMENTS = ("The results relate only to the item calibrated.",
              "This certificate shall not be reproduced except in full without the written approval of the "
              "issuing laboratory.")


@dataclass(frozen=True)
class Text:
    text: str
    note: bool = False  # small print beside a table or a figure


@dataclass(frozen=True)
class Heading:
    text: str


@dataclass(frozen=True)
class Fields:
    """Label-value pairs."""

    pairs: tuple[tuple[str, str], ...]


@dataclass(frozen=True)
class Grid:
    """A table: its header, its rows of text; per column the HTML class
    (``num``: right-aligned figures, ``hash``: a digest; other words name the
    column for a reader of the page); per row its HTML ``data-`` attributes;
    ``row_heads``: the first cell heads its row; ``folded``: the summary
    under which the HTML folds it away (the PDF prints it whole)."""

    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]
    classes: tuple[str, ...] = ()
    keys: tuple[tuple[tuple[str, str], ...], ...] = ()
    row_heads: bool = False
    folded: str | None = None

    def column_class(self, i: int) -> str:
        return self.classes[i] if i < len(self.classes) else ""


@dataclass(frozen=True)
class Figure:
    png: bytes
    alt: str


@dataclass(frozen=True)
class Preformatted:
    text: str
    folded: str | None = None


def _date_parts(iso: str) -> dict[str, int] | None:
    """An ISO 8601 UTC time as Typst's datetime arguments; None when there is none to read."""
    from datetime import datetime

    try:
        when = datetime.fromisoformat(iso.replace("Z", "+00:00"))
    except ValueError:
        return None
    return {"year": when.year, "month": when.month, "day": when.day, "hour": when.hour, "minute": when.minute,
            "second": when.second}


Block = Text | Heading | Fields | Grid | Figure | Preformatted


@dataclass(frozen=True)
class Section:
    title: str
    blocks: tuple[Block, ...]


@dataclass(frozen=True)
class Approval:
    """Who authorizes the certificate (ISO/IEC 17025:2017 7.8.2.1 o): name and function as given, or "not given"."""

    name: str
    function: str
    date_of_issue: str


@dataclass(frozen=True)
class Document:
    """The certificate: what every page's head says (laboratory, number),
    the main sections, the statements and approval, and the annex."""

    title: str
    subtitle: str
    laboratory: str
    number: str
    sections: tuple[Section, ...]
    approval: Approval
    annex: tuple[Section, ...]
    statements: tuple[str, ...] = STATEMENTS
    generated: str = ""
    created_utc: str = ""  # the run's time, ISO 8601: the PDF's document date

    def as_data(self, figure_name: Any) -> dict[str, Any]:
        """The document as JSON-ready data; ``figure_name(figure)`` names each figure's file."""
        def block(b: Block) -> dict[str, Any]:
            if isinstance(b, Figure):
                return {"type": "figure", "file": figure_name(b), "alt": b.alt}
            if isinstance(b, Grid):
                return {"type": "grid", "header": list(b.header), "rows": [list(r) for r in b.rows],
                        "numeric": [any(c in b.column_class(i).split() for c in ("num", "hash")) for i in range(len(b.header))],
                        "mono": [b.column_class(i) == "hash" for i in range(len(b.header))],
                        "row_heads": b.row_heads, "folded": b.folded}
            if isinstance(b, Fields):
                return {"type": "fields", "pairs": [list(p) for p in b.pairs]}
            if isinstance(b, Text):
                return {"type": "note" if b.note else "text", "text": b.text}
            if isinstance(b, Heading):
                return {"type": "heading", "text": b.text}
            return {"type": "pre", "text": b.text, "folded": b.folded}

        def section(s: Section) -> dict[str, Any]:
            return {"title": s.title, "blocks": [block(b) for b in s.blocks]}

        return {"title": self.title, "subtitle": self.subtitle, "laboratory": self.laboratory, "number": self.number,
                "sections": [section(s) for s in self.sections], "annex": [section(s) for s in self.annex],
                "statements": list(self.statements), "generated": self.generated,
                "created": _date_parts(self.created_utc),
                "approval": {"name": self.approval.name, "function": self.approval.function,
                             "date_of_issue": self.approval.date_of_issue}}
