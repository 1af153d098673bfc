"""The capture formats rotcal reads: one table (``REGISTRY``) of file suffix
-> its folder's reader, writer and block-by-block reader. Every question
"which format is this file" (finding a dataset's captures, reading one,
streaming one, writing one) is answered here and nowhere else
(``tests/test_formats_registry.py`` checks the package for other suffix tests).

A format is one folder beside this module (``csv/``, ``mcap/``, ``mat/``)
holding its reader, and its writer and block reader where it has them,
with the uniform signatures below, plus one line of ``REGISTRY``:

- reader: ``read_capture(path, spec, meta, limits, workers) -> (frame, notes)``,
  the columns of docs/inputs.md labelled by ``ingest.labels.label_columns``
  (or pose summaries, ``ingest.summaries``) and notes on the capture;
- writer: ``write_samples(samples, path) -> path``, a sample table
  (``t_ns``, ``u``, ``v``, ``w`` and the labels it has) as a capture;
- block reader: a module with ``open_capture(path, meta, spec, limits,
  workers, block, capture, messages) -> ingest.formats.blocks.RawStream``, the
  capture's samples in time order a block at a time, in memory bounded by
  the block, and ``message_counts(path, limits) -> list[int]``, each
  channel's messages counted without reading them (empty where they cannot
  be).

Nothing here imports the readers: the batch process finds the captures
(``ingest.files``) without loading polars; a format's modules load when a
capture of it is read.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import import_module
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class CaptureFormat:
    """One capture format: its name, file suffix (lower case), its folder
    (``package``), and where in that folder its reader, writer (None: rotcal
    writes none) and block reader (None: read whole) are, as
    ``"module:function"``."""

    name: str
    suffix: str
    package: str
    reads: str = "reader:read_capture"
    writes: str | None = "writer:write_samples"
    streams: str | None = None

    def _load(self, where: str) -> Callable[..., Any]:
        module, function = where.split(":")
        return getattr(import_module(f"{__name__}.{self.package}.{module}"), function)

    @property
    def reader(self) -> Callable[..., Any]:
        return self._load(self.reads)

    @property
    def writer(self) -> Callable[..., Any] | None:
        return None if self.writes is None else self._load(self.writes)

    @property
    def can_stream(self) -> bool:
        """Whether its captures are read block by block (else whole, then cut into blocks)."""
        return self.streams is not None

    @property
    def block_reader(self) -> Callable[..., Any] | None:
        return None if self.streams is None else self._load(f"{self.streams}:open_capture")

    def message_counts(self, path: Path, limits: Any) -> list[int]:
        """Each channel's messages in ``path`` counted without reading them
        (empty for a format read whole, or a file whose counts are not written)."""
        return [] if self.streams is None else self._load(f"{self.streams}:message_counts")(path, limits)


REGISTRY: tuple[CaptureFormat, ...] = (
    CaptureFormat("csv", ".csv", "csv", streams="blocks"),
    CaptureFormat("mcap", ".mcap", "mcap", streams="blocks"),
    CaptureFormat("mat", ".mat", "mat", writes=None),
)
# a capture named in dataset.toml [[capture]] with a suffix of no format (a logger's .txt or .log) is read as CSV
NAMED_DEFAULT = REGISTRY[0]
SUFFIXES = tuple(f.suffix for f in REGISTRY)


def format_of(path: Path | str) -> CaptureFormat | None:
    """The format of a file by its suffix (any case), None for a file of no capture format."""
    suffix = Path(path).suffix.lower()
    return next((f for f in REGISTRY if f.suffix == suffix), None)


def is_capture(path: Path | str) -> bool:
    """Whether a file found in a dataset directory is a capture (by its suffix)."""
    return format_of(path) is not None


def named_format(path: Path | str) -> CaptureFormat:
    """The format a capture named as such is read in: its suffix's, else CSV (``NAMED_DEFAULT``)."""
    return format_of(path) or NAMED_DEFAULT


def by_name(name: str) -> CaptureFormat:
    """The format called ``name`` (``csv``, ``mcap``, ``mat``)."""
    return next(f for f in REGISTRY if f.name == name)


def patterns() -> str:
    """The capture files' glob patterns, for messages: ``*.csv, *.mcap, ...``."""
    return ", ".join(f"*{s}" for s in SUFFIXES)
