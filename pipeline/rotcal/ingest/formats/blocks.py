"""A capture's samples a block at a time, before the time base: ``open_stream``
gives a ``RawStream`` whose ``blocks()`` yields the capture's canonical
sample columns (``COLUMNS``) in the order the file holds them, anew on each
call, and whose ``stamps()`` yields its stamps alone.

A format whose folder has a block reader (``ingest.formats``, ``can_stream``)
reads it in memory bounded by a block; it gives up on what it does not take
(``NotBlockwise``), and any other capture is read whole by its format's
reader (``read_whole``: the same values, and the same one-line message for
bad input, by construction) and cut into blocks. The time base is the next
stage's (``blockwise.repaired.repaired_stream``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.config import Limits
from rotcal.ingest.dataset import read_capture
from rotcal.ingest.formats import named_format
from rotcal.ingest.meta import CaptureSpec, DatasetMeta
from rotcal.ingest.summaries import MEANS
from rotcal.tables import conform

Blocks = Callable[[], Iterator[pl.DataFrame]]
Stamps = Callable[[], Iterator[np.ndarray]]
BLOCK_SAMPLES = 1 << 18
COLUMNS = ("t_ns", "u", "v", "w", "axis", "rate_hz", "angle_deg")  # the columns blocks carry


class NotBlockwise(Exception):
    """A capture its format's block reader does not take: it is read whole."""


@dataclass(frozen=True, eq=False)
class RawStream:
    """One capture's samples before the time base.

    ``capture`` is its name as ``load_dataset`` gives it, ``n_samples`` the
    rows in all, ``label_source`` where its labels came from, ``angle_source``
    the dataset's, ``notes`` those ``load_dataset`` adds for it. A capture
    read block by block (``bounded``) gives ``blocks()`` (``COLUMNS``, the
    ``samples`` contract's types, in the file's order), ``stamps()`` and
    ``ties``: where stamps repeat, the positions of both samples and their
    channels (n x 3), the only values the time base's duplicate check reads;
    None where no stamp repeats. A capture read whole holds its samples in
    ``whole`` (conformed, with ``capture``) and says why in ``whole_because``.
    ``read_whole()`` reads it whole (for a time base that needs a sort).
    """

    capture: str
    n_samples: int
    label_source: str | None
    angle_source: str
    notes: tuple[str, ...]
    read_whole: Callable[[], RawStream]
    blocks: Blocks = lambda: iter(())
    stamps: Stamps = lambda: iter(())
    ties: tuple[np.ndarray, np.ndarray] | None = None
    whole: pl.DataFrame | None = None
    whole_because: str | None = None
    _files: tuple = field(default=(), repr=False)  # the spills (``ingest.spill``), removed with the stream

    @property
    def bounded(self) -> bool:
        return self.whole is None


def read_whole(path: Path, meta: DatasetMeta, spec: CaptureSpec | None, limits: Limits, workers: int,
               capture: str, because: str | None = None) -> RawStream:
    """The capture read whole (``ingest.dataset.read_capture``), as ``load_dataset``
    reads it, ``because`` the reason it is not read block by block."""
    frame, notes = read_capture(path, spec, meta, limits, workers)
    if MEANS[0] in frame.columns:
        raise NotBlockwise("it holds pose summaries, not samples")
    samples = conform(frame.with_columns(capture=pl.lit(capture)), "samples")
    source = next(iter(samples["label_source"].drop_nulls()), None)

    def again() -> RawStream:
        return read_whole(path, meta, spec, limits, workers, capture, because)
    return RawStream(capture, samples.height, source, meta.angle_source, notes, again, whole=samples, whole_because=because)


def open_stream(path: Path, meta: DatasetMeta, spec: CaptureSpec | None = None, limits: Limits = Limits(),
                workers: int = 0, block_samples: int = BLOCK_SAMPLES, capture: str | None = None,
                messages: int | None = None) -> RawStream:
    """One capture file of a dataset (``meta`` its ``dataset.toml``, ``spec``
    its ``[[capture]]`` entry), block by block where its format can
    (``block_samples`` rows a block), on ``parallel.cores(workers)`` cores.
    ``capture`` is its name in the dataset (``load_dataset``: the path
    relative to the dataset's root; default the file's name); ``messages``,
    the file's messages of every channel where the caller has counted them.
    Bad input raises the ``InputError`` the in-memory reader raises."""
    path = Path(path)
    capture = capture or path.name
    fmt = named_format(path)
    because = f"{fmt.name.upper()} captures have no block reader"
    if fmt.block_reader is not None:
        try:
            return fmt.block_reader(path, meta, spec, limits, workers, block_samples, capture, messages)
        except NotBlockwise as exc:
            because = f"a {fmt.name.upper()} capture its block reader does not take: {exc}"  # read below, outside the handler
    return read_whole(path, meta, spec, limits, workers, capture, because)
