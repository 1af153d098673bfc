"""The text layout of one CSV capture (docs/inputs.md, ``[format]``): the
lines to skip, the comment prefix, the field separator and the decimal mark,
as given in ``dataset.toml`` or detected from the file's first lines.

Detection reads at most ``SNIFF_BYTES`` after the skipped lines, so it costs
the same on a file of a thousand rows or of a hundred million.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from itertools import islice
from pathlib import Path
from typing import BinaryIO

from rotcal.errors import InputError
from rotcal.ingest.meta import CsvFormat

SNIFF_BYTES = 1 << 16
SNIFF_LINES = 20
# tried in this order: a semicolon file writes decimal commas, so a comma is a
# separator only where no semicolon or tab separates the fields consistently
SEPARATORS = ((";", "semicolon"), ("\t", "tab"), (",", "comma"))
_DECIMAL_COMMA = re.compile(rb"\d,\d")


@dataclass(frozen=True)
class Layout:
    """How polars reads the text: ``whitespace`` files are first rewritten
    with ``separator`` between their fields (``csv_source``)."""

    separator: str
    whitespace: bool
    decimal_comma: bool
    skip_lines: int
    comment_prefix: str | None

    def read_options(self) -> dict:
        return {"separator": self.separator, "skip_lines": self.skip_lines, "comment_prefix": self.comment_prefix,
                "decimal_comma": self.decimal_comma}


def _offset_after(fh: BinaryIO, lines: int, path: Path) -> int:
    """The byte offset of line ``lines`` (0-based), refused when the file
    has no text there."""
    size = fh.seek(0, 2)
    fh.seek(0)
    offset, seen = 0, 0
    while block := fh.read(SNIFF_BYTES):
        count = block.count(b"\n")
        if seen + count >= lines:
            pos = -1
            for _ in range(lines - seen):
                pos = block.index(b"\n", pos + 1)
            if offset + pos + 1 < size:
                return offset + pos + 1
        seen, offset = seen + count, offset + len(block)
    fh.seek(size - 1)
    total = seen + (fh.read(1) != b"\n")
    raise InputError(f"dataset.toml [format] skip_lines = {lines} skips the whole file (it has {total} lines)", path=path)


def _sample_lines(fh: BinaryIO, start: int, comment: str | None) -> list[bytes]:
    """Up to ``SNIFF_LINES`` lines from ``start``: no comments, no blank lines,
    no line cut by the end of the sample."""
    fh.seek(start)
    text = fh.read(SNIFF_BYTES)
    lines = text.split(b"\n")
    if len(text) == SNIFF_BYTES and len(lines) > 1:
        lines = lines[:-1]
    prefix = comment.encode() if comment else None
    kept = (line.rstrip(b"\r") for line in lines if line.strip() and not (prefix and line.lstrip().startswith(prefix)))
    return list(islice(kept, SNIFF_LINES))  # stops at the last line kept: a sample holds thousands


def _splits(sep: str, lines: list[bytes], header: bool) -> bool:
    """Whether ``sep`` splits every line into the same number (two or more)
    of fields; a comma, only where no data field holds a blank between two
    values (``0.00  15765,25  288,50``: blanks separate, commas are decimal)."""
    counts = {line.count(sep.encode()) for line in lines}
    if len(counts) != 1 or counts.pop() == 0:
        return False
    data = lines[1:] if header else lines
    return sep != "," or not any(len(field.split()) > 1 for line in data for field in line.split(b","))


def _separator(lines: list[bytes], header: bool, path: Path) -> str:
    """The separator that splits every sample line into the same number
    (two or more) of fields; ``whitespace`` when only runs of blanks do."""
    for sep, _ in SEPARATORS:
        if _splits(sep, lines, header):
            return sep
    fields = {len(line.split()) for line in lines}
    if len(fields) == 1 and fields.pop() > 1:
        return "whitespace"
    _ragged(lines, path)
    tried = ", ".join(name for _, name in SEPARATORS)
    first = lines[0][:60].decode("utf-8", "replace")
    raise InputError(f"cannot detect the delimiter: no {tried} or whitespace splits the first {len(lines)} lines into "
                     f"the same number of fields (first line {first!r})", path=path,
                     hint="set dataset.toml [format] delimiter, or skip_lines for a preamble before the header")


def _ragged(lines: list[bytes], path: Path) -> None:
    """Refuse, naming it, a line with fewer or more fields than all the
    others have by one separator: the delimiter is known then, the line is
    what is wrong (a row cut short, a stray field)."""
    if len(lines) < 3:
        return
    for sep, name in SEPARATORS:
        counts = [line.count(sep.encode()) for line in lines]
        usual = max(set(counts), key=counts.count)
        odd = [k for k, c in enumerate(counts) if c != usual]
        if usual > 0 and len(odd) == 1:
            line = lines[odd[0]][:60].decode("utf-8", "replace")
            hint = ("a preamble before the header? set dataset.toml [format] skip_lines" if odd[0] == 0
                    else "complete or remove that line")
            raise InputError(f"a line has {counts[odd[0]] + 1} {name}-separated fields where the other lines have "
                             f"{usual + 1}: {line!r}", path=path, hint=hint)


def layout(fh: BinaryIO, fmt: CsvFormat, path: Path) -> Layout:
    """The layout of the file open as ``fh``: ``fmt``'s keys, and what they
    leave open detected from the first lines after ``skip_lines``."""
    start = _offset_after(fh, fmt.skip_lines, path) if fmt.skip_lines else 0
    lines = [] if fmt.delimiter is not None and fmt.decimal_comma is not None else _sample_lines(fh, start, fmt.comment_prefix)
    delimiter = fmt.delimiter if fmt.delimiter is not None else (_separator(lines, fmt.header, path) if lines else ",")
    decimal_comma = fmt.decimal_comma
    if decimal_comma is None:
        rows = lines[1:] if fmt.header else lines
        decimal_comma = delimiter != "," and any(_DECIMAL_COMMA.search(line) for line in rows)
    whitespace = delimiter == "whitespace"
    separator = (";" if decimal_comma else ",") if whitespace else delimiter
    if decimal_comma and separator == ",":
        raise InputError("dataset.toml [format] decimal = \",\" needs a delimiter other than a comma", path=path)
    return Layout(separator, whitespace, decimal_comma, fmt.skip_lines, fmt.comment_prefix)
