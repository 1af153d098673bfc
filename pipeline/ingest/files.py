"""Capture files as the file system holds them: a name is opened as it is
written (``x[yz].csv`` is that file, never a glob pattern matching
``xz.csv``), and only a regular file is read (a FIFO would block the run
forever waiting for a writer, a device would never end)."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from rotcal.errors import InputError

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


def open_capture(path: Path) -> BinaryIO:
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
