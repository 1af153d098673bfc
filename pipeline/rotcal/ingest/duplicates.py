"""Copied captures: the same bytes under two names in one dataset. Read
twice, every sample would be a duplicate of itself: thousands of one-sample
segments and as many warnings, where one copy gives the right result."""

from __future__ import annotations

import hashlib
import os
from collections import defaultdict
from collections.abc import Mapping
from pathlib import Path
from typing import TypeVar

from rotcal.ingest.files import open_capture

Spec = TypeVar("Spec")


def sha256_hex(path: Path) -> str:
    """The SHA-256 of a file's bytes (hex), read in blocks."""
    with open_capture(path) as fh:
        return hashlib.file_digest(fh, "sha256").hexdigest()


def file_identity(st: os.stat_result) -> tuple[int, int, int, int, int]:
    """A file's device, inode, size, mtime and ctime (ns): unchanged, so is
    its content (when it was last changed well before it was hashed: the
    batch's rule, ``batch.manifest.RACY_NS``)."""
    return st.st_dev, st.st_ino, st.st_size, st.st_mtime_ns, st.st_ctime_ns


def content_hashes(files: tuple[Path, ...], root: Path, known: Mapping[tuple[int, ...], str] | None = None) -> tuple[dict, ...]:
    """Each file's path (relative to ``root``; absolute when outside it, as
    a ``--meta`` file may be), size in bytes and SHA-256: what identifies a
    run's inputs (calibration.json's ``inputs``). ``known``: SHA-256s the
    caller has, by ``file_identity``, taken for a file that still has it
    instead of reading it again (the batch hashed every input to plan)."""
    top = root.resolve()

    def name(f: Path) -> str:
        resolved = f.resolve()
        return (resolved.relative_to(top) if resolved.is_relative_to(top) else resolved).as_posix()

    def entry(f: Path) -> dict:
        st = f.stat()
        return {"path": name(f), "bytes": st.st_size, "sha256": (known or {}).get(file_identity(st)) or sha256_hex(f)}

    return tuple(entry(f) for f in files)


def distinct_captures(files: list[tuple[Path, Spec]], root: Path) -> tuple[list[tuple[Path, Spec]], tuple[tuple[str, str], ...]]:
    """``files`` without the copies of an earlier one, and each copy skipped
    as (its name, the name of the file it copies), relative to ``root``.
    Only files of equal size are hashed (SHA-256, in blocks), so a dataset
    without copies costs a ``stat`` per file."""
    by_size: defaultdict[int, list[int]] = defaultdict(list)
    for i, (file, _) in enumerate(files):
        by_size[file.stat().st_size].append(i)
    original: dict[int, int] = {}  # copy -> the file it copies
    for group in (g for g in by_size.values() if len(g) > 1):
        first: dict[str, int] = {}
        for i in group:
            original[i] = first.setdefault(sha256_hex(files[i][0]), i)
    copies = sorted(i for i, j in original.items() if i != j)

    def name(i: int) -> str:
        return Path(os.path.relpath(files[i][0].resolve(), root.resolve())).as_posix()

    skipped = set(copies)
    return [f for i, f in enumerate(files) if i not in skipped], tuple((name(i), name(original[i])) for i in copies)


def duplicate_findings(dataset: str, copies: tuple[tuple[str, str], ...]) -> list[dict]:
    """One ``duplicate_capture`` row of the time-base table per copy skipped."""
    return [{"dataset": dataset, "capture": copy, "check": "duplicate_capture", "detected": True, "value": 1.0,
             "std_uncertainty": None, "unit": "1", "action": "dropped: the copy is not read",
             "evidence": f"{copy!r} holds the same bytes as {original!r} (SHA-256): read once"} for copy, original in copies]
