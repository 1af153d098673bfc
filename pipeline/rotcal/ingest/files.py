"""Capture files as the file system holds them: a dataset's captures
(``capture_files``) stay inside its directory, a name is opened as it is
written (``x[yz].csv`` is that file, never a glob pattern matching
``xz.csv``), and only a regular file is read (a FIFO would block the run
forever waiting for a writer, a device would never end). Nothing here loads
Polars: the batch process finds a dataset's captures with it."""

from __future__ import annotations

import io
import os
import stat
from pathlib import Path
from typing import TYPE_CHECKING

from rotcal.errors import InputError
from rotcal.ingest.formats import is_capture, patterns

if TYPE_CHECKING:
    from rotcal.ingest.meta import CaptureSpec, DatasetMeta

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


def _refuse_irregular(mode: int, path: Path) -> None:
    if not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "not a file")
        raise InputError(f"not a regular file ({kind}): a capture must be a file", path=path)


def require_regular(path: Path) -> None:
    """Refuse ``path`` unless it is, after links, a regular file (by
    ``os.stat``: nothing is opened)."""
    try:
        _refuse_irregular(os.stat(path).st_mode, path)
    except OSError as exc:
        raise InputError(f"cannot be read: {exc.strerror}", path=path) from None


def open_capture(path: Path) -> io.BufferedReader:
    """``path`` opened for binary reading, refused unless a regular file.

    Opened without blocking (a FIFO's open would wait for a writer) and
    checked with ``fstat`` on the open descriptor, so the file checked is
    the file read even if the name is swapped in between.
    """
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise InputError(f"cannot be opened: {exc.strerror}", path=path) from None
    try:
        _refuse_irregular(os.fstat(fd).st_mode, path)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def dataset_name(path: Path) -> str:
    return path.name if path.is_dir() else path.stem


def inside(root: Path, relative: str, source: str | None) -> Path:
    """``root / relative``, refused unless it stays inside ``root`` (no ``..``,
    absolute paths or symlinks out)."""
    candidate = Path(relative)
    resolved = (root / candidate).resolve()
    if candidate.is_absolute() or not resolved.is_relative_to(root.resolve()):
        raise InputError(f"[[capture]] file {relative!r} points outside the dataset directory", path=source)
    return resolved


def capture_files(path: Path, meta: DatasetMeta) -> list[tuple[Path, CaptureSpec | None]]:
    """The dataset's captures with their ``[[capture]]`` entries, by file name.

    Every capture must be a regular file (a FIFO named ``trap.csv`` is
    refused, not waited on) inside the dataset directory: a link found in
    the directory whose target resolves outside it is refused with one line,
    as a ``[[capture]]`` entry pointing outside is; skipping it would
    calibrate from fewer captures than the directory shows. A capture file
    given itself (not a directory) is read wherever its link points.
    """
    if not path.is_dir():
        require_regular(path)
        specs = {c.file: c for c in meta.captures}
        return [(path, specs.get(path.name))]
    if meta.captures:
        files: list[tuple[Path, CaptureSpec | None]] = [(inside(path, c.file, meta.source), c) for c in meta.captures]
        for file, _ in files:
            if not os.path.exists(file):  # False, not OSError, for a name too long to exist
                raise InputError("capture file named in dataset.toml does not exist", path=file)
            require_regular(file)
        return files
    found = sorted(p for p in path.iterdir() if is_capture(p) and not p.is_dir())
    if not found:
        raise InputError(f"no capture files ({patterns()}) in the dataset directory", path=path)
    resolved = path.resolve()
    for file in found:  # an entry that is no link lies in the directory: only a link can lead out of it
        if file.is_symlink() and not file.resolve().is_relative_to(resolved):
            raise InputError(f"{file.name!r} is a symbolic link pointing outside the dataset directory", path=file)
        require_regular(file)
    return [(f, None) for f in found]
