"""A capture's sample blocks after its time base: ``repaired_stream`` takes
ingest's ``RawStream`` (``ingest.formats.blocks.open_stream``) and gives a
``StreamedCapture`` whose blocks are repaired as ``repair_timebase``
repairs the whole sample table: the time base checked on the stamps alone
where it can be (``stream_grid``), else with the stamps in memory
(``streamed.held``), else, for a capture read whole or one whose repaired
stamps need a sort, on the whole capture."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field, replace

import numpy as np
import polars as pl

from rotcal.blockwise.grid import stream_grid
from rotcal.blockwise.timebase import AtTies, NotSorted, StreamedTimebase, held, loaded, outcome
from rotcal.ingest.formats.blocks import BLOCK_SAMPLES, COLUMNS, Blocks, RawStream
from rotcal.ingest.labels import time_ordered
from rotcal.model.physics import CHANNELS
from rotcal.timebase.check import TimebaseConfig, check_capture


@dataclass(frozen=True, eq=False)
class StreamedCapture:
    """One capture's samples after the time base, block by block.

    ``capture``, ``label_source``, ``angle_source`` and ``notes`` are the
    ``RawStream``'s, ``n_samples`` the rows ``blocks()`` yields in all
    (after the time base), ``timebase`` its time base (findings, warnings,
    gaps), and ``blocks()`` the repaired sample blocks (``COLUMNS``) in time
    order, anew on each call. ``bounded`` is False where the capture was
    read whole, and why (``whole_because``).
    """

    capture: str
    n_samples: int
    label_source: str | None
    angle_source: str
    notes: tuple[str, ...]
    timebase: StreamedTimebase
    blocks: Blocks
    bounded: bool = True
    whole_because: str | None = None
    _raw: RawStream | None = field(default=None, repr=False)  # holds the spills while the capture is read


def _timebase(raw: RawStream, config: TimebaseConfig) -> StreamedTimebase:
    """The time base from the stamps: streamed, else (repeated stamps) with the stamps in memory."""
    if raw.ties is None:
        streamed = stream_grid(raw.stamps, raw.n_samples, raw.capture, config)
        if streamed is not None:
            return streamed
    at, values = raw.ties if raw.ties is not None else (np.zeros(0, np.int64), np.zeros((0, 3)))
    channels = [AtTies(at, values[:, c]) for c in range(3)]
    return held(check_capture(loaded(raw.stamps), channels, raw.capture, config), raw.capture)


def _whole(raw: RawStream, config: TimebaseConfig, block: int) -> StreamedCapture:
    """A capture read whole: its time base checked and repaired in memory
    (``check_capture``, ordered as ``repair_timebase`` orders it), cut into blocks."""
    samples = raw.whole
    assert samples is not None
    tb = check_capture(samples["t_ns"].to_numpy(), [samples[c].to_numpy() for c in CHANNELS], raw.capture, config)
    repaired = samples.filter(pl.Series(tb.keep)).with_columns(t_ns=pl.Series(tb.t_ns, dtype=pl.Int64))
    whole = time_ordered(repaired).select(COLUMNS)

    def blocks() -> Iterator[pl.DataFrame]:
        for a in range(0, whole.height, block):
            yield whole.slice(a, block)
    return StreamedCapture(raw.capture, whole.height, raw.label_source, raw.angle_source, raw.notes, outcome(tb, raw.capture),
                           blocks, bounded=False, whole_because=raw.whole_because)


def repaired_stream(raw: RawStream, config: TimebaseConfig = TimebaseConfig(),
                    block_samples: int = BLOCK_SAMPLES) -> StreamedCapture:
    """A capture's samples (``ingest.formats.blocks.open_stream``) after its time
    base: checked on the stamps, and each block of a pass repaired in order;
    a capture read whole, or whose repaired stamps need a sort, is checked
    and repaired whole and cut into blocks of ``block_samples``."""
    if raw.bounded:
        try:
            timebase = _timebase(raw, config)
        except NotSorted:
            raw = replace(raw.read_whole(), whole_because="repaired time stamps out of order: they are sorted whole")
        else:
            def blocks() -> Iterator[pl.DataFrame]:
                repair = timebase.repairer()
                for frame in raw.blocks():
                    yield repair(frame)
            return StreamedCapture(raw.capture, timebase.n_kept, raw.label_source, raw.angle_source, raw.notes, timebase,
                                   blocks, _raw=raw)
    return _whole(raw, config, block_samples)
