"""The run's load and segment stages, block by block: a capture's samples
are not held; the segment stage reads them in passes (``blockwise.segments``)
and keeps only what the later stages read: the static segments' samples,
the diagnosis's thinned rows, each fitted segment's sums and the noise
model's pooled residual statistics. The tables are those of the same
functions on the samples held whole (``[run] stream_above_samples`` N > 0
reads captures of at most N samples whole, as a check).

What the block path does not take is read whole, each for its reason
(a note ``read in memory, not block by block: <why>``
says so for a single capture):

- datasets of several captures, or of pose summaries: the samples of
  several files are ordered and checked together (``ingest.dataset``);
- a format without a block reader (MATLAB ``.mat``: scipy reads the file
  whole), or a capture its block reader does not take (``ingest.formats.blocks.
  NotBlockwise``: MCAP JSON messages or out-of-order chunks, CSV layouts
  other than plain labelled columns);
- repaired stamps that need a sort (``blockwise.repaired``);
- and what the later stages read whole (``why_not``): four-parameter fits
  (the rate refitted against every sample), unlabelled samples or no
  table angle (segments found in the signals), gaps in the time base
  (classified by the segments on both sides).
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import polars as pl

from rotcal.blockwise.repaired import repaired_stream
from rotcal.blockwise.segments import Blocks, StreamedSegments, stream_segments, with_segments
from rotcal.config import RunConfig
from rotcal.fit.segments import SegmentFit
from rotcal.ingest.dataset import Dataset, load_dataset
from rotcal.ingest.files import capture_files, dataset_name
from rotcal.ingest.formats import named_format
from rotcal.ingest.formats.blocks import BLOCK_SAMPLES, NotBlockwise, open_stream
from rotcal.ingest.meta import load_meta
from rotcal.model.physics import CHANNELS
from rotcal.tables import schema
from rotcal.timebase.repair import TimebaseResult

if TYPE_CHECKING:
    from rotcal.diagnose import Diagnosis


@dataclass(frozen=True, eq=False)
class StreamedDataset(Dataset):
    """A dataset whose samples are read block by block: ``blocks`` yields
    them anew for each pass, after the time base (``timebase``, whose
    ``samples`` are not held); ``in_memory`` reads the dataset whole when
    the streamed path cannot take it."""

    blocks: Blocks = lambda: iter(())
    timebase: TimebaseResult | None = None
    in_memory: Callable[[], Dataset] | None = None


def load(path: Path, meta_path: Path | None, config: RunConfig) -> Dataset:
    """The dataset, its samples streamed (``ingest.formats.blocks.open_stream``,
    repaired by ``blockwise.repaired.repaired_stream``) when it is one capture
    (of more than ``[run] stream_above_samples`` samples) whose format's
    block reader takes it (``ingest.formats``: MCAP and CSV); read whole
    otherwise, a single capture with a note saying why (the module's list)."""
    path = Path(path)
    if meta_path is None and path.is_dir() and (path / "dataset.toml").is_file():
        meta_path = path / "dataset.toml"
    whole = partial(load_dataset, path, meta_path, config.limits, config.run.workers)
    if not path.exists():
        return whole()  # the in-memory reader words the problem
    meta = load_meta(meta_path)
    root = path if path.is_dir() else path.parent
    files = capture_files(path, meta)
    counts = named_format(files[0][0]).message_counts(files[0][0], config.limits) if len(files) == 1 else []
    if max(counts, default=0) <= config.run.stream_above_samples:
        return whole()
    file, spec = files[0]
    capture = Path(os.path.relpath(file.resolve(), root.resolve())).as_posix()
    try:
        raw = open_stream(file, meta, spec, config.limits, config.run.workers, BLOCK_SAMPLES, capture, messages=sum(counts))
    except NotBlockwise:  # pose summaries: no samples to stream (the module's list)
        return whole()
    # read in memory by the stream's reader (or, repaired, sorted whole): the dataset's reader keeps every column;
    # a capture read whole gets its time base there, not here as well
    stream = repaired_stream(raw, block_samples=BLOCK_SAMPLES) if raw.bounded else None
    if stream is None or not stream.bounded:
        because = raw.whole_because if stream is None else stream.whole_because
        del raw, stream  # not held while the dataset is read again
        read = whole()
        return replace(read, notes=(*read.notes, f"read in memory, not block by block: {because} (docs/streaming.md)"))
    constant = [pl.lit(capture, pl.Categorical).alias("capture"), pl.lit(None, pl.Float64).alias("temperature_c"),
                pl.lit(stream.label_source or "file", schema("samples").polars_schema["label_source"]).alias("label_source")]
    tb = stream.timebase
    timebase = TimebaseResult(schema("samples").empty(), tb.findings_table(dataset_name(path)), tb.warnings,
                              {capture: tb.unrepairable} if tb.unrepairable else {}, () if tb.gaps is None else (tb.gaps,))
    return StreamedDataset(dataset_name(path), root, meta, schema("samples").empty(), (*meta.notes, *stream.notes),
                           inputs=(file, *(() if meta_path is None else (Path(meta_path),))),
                           blocks=lambda: (b.with_columns(constant) for b in stream.blocks()), timebase=timebase,
                           in_memory=whole)


def why_not(ds: StreamedDataset, config: RunConfig, streamed: StreamedSegments | None = None) -> str | None:
    """Why the streamed path cannot take a dataset (None: it can): it fits
    three parameters against a table angle to labelled samples of one
    capture whose time base has no gap to classify; blind segmentation,
    four-parameter fits and gaps read every sample."""
    timebase = ds.timebase
    assert timebase is not None
    if config.fit.sine_fit != "three_parameter":
        return "four-parameter fits ([fit] sine_fit)"
    if ds.meta.angle_source == "none":
        return "no table angle (angle_source = \"none\")"
    if timebase.unrepairable or any(g.length.size for g in timebase.gaps):
        return "gaps in the time base"
    if streamed is not None and (streamed.unlabelled or (streamed.segments["angle_source"] == "none").any()):
        return "samples without axis, rate or angle labels"
    if streamed is not None and streamed.segments.filter(pl.col("kind").is_in(["static", "rotation"])).is_empty():
        return "no static or rotation segments"
    return None


def streamed_segments(ds: StreamedDataset, config: RunConfig) -> tuple[StreamedSegments | None, tuple[str, ...]]:
    """The segments and fits of a streamed dataset, or None with a note
    when the streamed path cannot take it."""
    reason = why_not(ds, config)
    streamed = None
    if reason is None:
        streamed = stream_segments(ds.blocks, ds.name, ds.meta.angle_source, config.fit, config.diagnosis.max_samples)
        reason = why_not(ds, config, streamed)
    if reason is None:
        return streamed, ()
    return None, (f"read in memory, not block by block: {reason}",)


def streamed_fits(blocks: Blocks, ds: Dataset, config: RunConfig) -> list[SegmentFit]:
    """The segment fits of a capture's blocks (``corrected_blocks``'s: the fits under the refined model)."""
    return stream_segments(blocks, ds.name, ds.meta.angle_source, config.fit, config.diagnosis.max_samples, pool_noise=False).fits


def corrected_blocks(streamed: StreamedSegments, segments: pl.DataFrame, fits: pl.DataFrame, diagnosis: Diagnosis) -> Blocks:
    """The blocks less the modelled effects' contribution: block by block,
    what ``diagnose.corrected.without_effects`` does to the whole sample
    table. Each block's samples of the diagnosed segments are modelled with
    what the model takes from outside the block: the capture's first sample
    (the time origin) and each segment's first (its start angle)."""
    from rotcal.diagnose.model import Structure, predict
    from rotcal.diagnose.observed import observations

    final = diagnosis.final
    diagnosed = np.unique(final.obs.segment)
    first = {int(s): streamed.sizes[int(s)][0] for s in diagnosed}
    heads = streamed.gathered.filter(pl.col("row").is_in([0, *first.values()]))

    def corrected(block: pl.DataFrame, offset: int) -> pl.DataFrame:
        framed = with_segments(block.with_columns(row=pl.int_range(offset, offset + block.height, dtype=pl.Int64)),
                               streamed.sizes)
        present = [s for s in framed["segment"].unique(maintain_order=True).drop_nulls().to_list() if s in first]
        if not present:
            return block
        # each diagnosed segment's rows contiguous and in time order, its first sample before them
        groups = [] if heads["segment"][0] in present else [heads.head(1)]
        for s in present:
            groups += [heads.filter((pl.col("row") == first[s]) & (pl.col("row") < offset)),
                       framed.filter(pl.col("segment") == s)]
        frame = pl.concat(groups)
        in_frame = fits.filter(pl.col("segment").is_in(frame["segment"].drop_nulls().implode()))
        built = observations(frame, segments, in_frame, final.obs.rates.tolist(), final.obs.g_local, frame.height)
        assert built is not None
        obs = built[0]
        effect = (predict(obs, final.beta, final.layout, final.active, final.clip, final.structure)
                  - predict(obs, final.beta, final.layout, (), (None, None), Structure()))
        # observations orders rows by (rate, time): by segment (stable), each segment's rows in frame order
        segment, row = frame["segment"].to_numpy(), frame["row"].to_numpy()
        rows = np.concatenate([row[segment == s] for s in np.unique(obs.segment)])
        effect = effect[np.argsort(obs.segment, kind="stable")]
        inside = rows >= offset
        y = block.select(CHANNELS).to_numpy().copy()
        y[rows[inside] - offset] -= effect[inside]
        return block.with_columns(pl.Series(c, y[:, i]) for i, c in enumerate(CHANNELS))

    def blocks() -> Iterator[pl.DataFrame]:
        offset = 0
        for block in streamed.blocks():
            yield corrected(block, offset)
            offset += block.height

    return blocks
