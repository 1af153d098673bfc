"""A dataset (a directory or a single capture file, with its
``dataset.toml``) read into the canonical sample table, whatever the
formats of its captures."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import polars as pl

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.duplicates import distinct_captures
from rotcal.ingest.files import capture_files, dataset_name
from rotcal.ingest.formats import named_format
from rotcal.ingest.formats.csv.joined import read_joined
from rotcal.ingest.labels import time_ordered
from rotcal.ingest.meta import CaptureSpec, DatasetMeta, load_meta
from rotcal.ingest.summaries import MEANS
from rotcal.tables import conform, schema


@dataclass(frozen=True)
class Dataset:
    """One DUT's calibration data: name, metadata and canonical samples."""

    name: str
    root: Path
    meta: DatasetMeta
    samples: pl.DataFrame
    notes: tuple[str, ...] = ()
    copies: tuple[tuple[str, str], ...] = ()  # captures skipped as copies: (copy, the file it copies)
    inputs: tuple[Path, ...] = ()  # every file the dataset is (captures, copies included, and its dataset.toml)
    summaries: pl.DataFrame | None = None  # pose summaries (ingest.summaries) instead of samples


def read_capture(file: Path, spec: CaptureSpec | None, meta: DatasetMeta, limits: Limits,
                 workers: int = 0) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """One capture and notes on it, read by its format's reader
    (``ingest.formats.named_format``); ``workers`` as ``parallel.cores`` reads it."""
    return named_format(file).reader(file, spec, meta, limits, workers)


def load_dataset(path: Path, meta_path: Path | None = None, limits: Limits = Limits(), workers: int = 0) -> Dataset:
    """Read every capture of a dataset into the canonical sample table, on
    ``parallel.cores(workers)`` cores.

    ``meta_path`` replaces the dataset's own ``dataset.toml`` (``--meta``).
    Captures share one clock; samples are sorted by time, stably.
    """
    path = Path(path)
    if not path.exists():
        raise InputError("dataset not found", path=path)
    if meta_path is None and path.is_dir() and (path / "dataset.toml").is_file():
        meta_path = path / "dataset.toml"
    meta = load_meta(meta_path)
    root = path if path.is_dir() else path.parent
    files = capture_files(path, meta)
    captures, copies = distinct_captures(files, root)
    resolved_root = root.resolve()
    names = [Path(os.path.relpath(file.resolve(), resolved_root)).as_posix() for file, _ in captures]
    inputs = tuple(f for f, _ in files) + (() if meta_path is None else (Path(meta_path),))
    frames, summaries, notes = [], {}, [*meta.notes, *(f"duplicate capture: {c!r} holds the same bytes as {o!r}: "
                                                       f"read once, {c!r} skipped" for c, o in copies)]
    plain = read_joined(captures, names, meta.csv_format, limits)  # None: read capture by capture
    if plain is not None:
        frames.append(plain)
    for (file, spec), name in zip(captures if plain is None else (), names):
        frame, capture_notes = read_capture(file, spec, meta, limits, workers)
        notes += capture_notes
        if MEANS[0] in frame.columns:
            summaries[name] = frame
        else:
            frames.append(conform(frame.with_columns(capture=pl.lit(name)), "samples"))  # categorical before concat
        del frame  # not held past its capture: its columns' chunks go when they are made one below
    if summaries and frames:
        raise InputError(f"{next(iter(summaries))!r} holds pose summaries and {frames[0]['capture'][0]!r} samples: "
                         "a dataset is one or the other", path=path)
    if summaries:
        return Dataset(name=dataset_name(path), root=root, meta=meta, samples=schema("samples").empty(),
                       notes=tuple(notes), copies=copies, inputs=inputs, summaries=pl.concat(summaries.values()))
    joined = frames[0] if len(frames) == 1 else pl.concat(frames)  # concat would materialise constant columns
    samples = conform(time_ordered(joined), "samples")
    del frames, plain, joined
    # each column in one chunk, a column at a time: every stage's numpy arrays of it are then views, not copies
    for name in samples.columns:
        if samples[name].n_chunks() > 1:
            samples = samples.with_columns(samples[name].rechunk())
    return Dataset(name=dataset_name(path), root=root, meta=meta, samples=samples, notes=tuple(notes), copies=copies,
                   inputs=inputs)
