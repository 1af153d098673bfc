"""Publishing an output directory whole, so that it holds one run.

Everything a run writes goes into a staging directory beside the target
(same parent, hence same file system), with a listing of the files it holds
(``rotcal-files.json``, ``schemas/rotcal_files.json``); then the old
directory is renamed aside, the staging one renamed into place and the old
one removed. rename(2) within one file system is atomic (POSIX), so a reader
sees the old output or the new one, never a mixture, and nothing of an
earlier run survives beside the new one. Only what a listing says rotcal
wrote (same name, size and SHA-256) is replaced without being told
(``replace``): any other file makes the target refused. The staging and
aside directories of a killed run are named after their target and the
process that made them, and removed by the next publication into the same
target once that process is gone.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from rotcal import __version__
from rotcal.errors import InputError
from rotcal.jsontext import json_text

if TYPE_CHECKING:
    import pyarrow as pa

LISTING = "rotcal-files.json"
LISTING_SCHEMA = ("rotcal_files", "1.0")
_KINDS = ("staging", "old")  # the two temporary directories beside a target


@dataclass(frozen=True)
class OutputDir:
    """Where a run publishes, and whether files no rotcal listing names may be replaced there."""

    path: Path
    replace: bool = False
    # called with each table as it is published (its name, its Arrow table):
    # the batch writes its parts from them without reading the files back
    on_table: Callable[[str, pa.Table], object] | None = None


def usable(path: Path, swapped: bool = True) -> Path:
    """``path``, absolute with its links resolved, if output can be written
    there: a directory, or one that can be made (its nearest existing
    ancestor a directory this user may write into). ``swapped``: the
    directory is replaced by renames, which need its parent writable too
    (and the directory itself, whose ``..`` entry a rename rewrites:
    rename(2), EACCES). Raises ``InputError`` naming ``path``."""
    try:
        target = Path(path).resolve()
    except (OSError, RuntimeError) as exc:  # a loop of links (RuntimeError before Python 3.13)
        raise InputError(f"output directory cannot be resolved: {exc}", path=path) from None
    existing = target
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        problem = "is not a directory" if existing == target else f"cannot be made: {existing} is not a directory"
        raise InputError(f"output directory {problem}", path=path)
    if swapped and target == target.parent:
        raise InputError("output directory cannot be the root of the file system (a run is renamed into place beside it)",
                         path=path)
    if not os.access(existing, os.R_OK | os.W_OK | os.X_OK):
        where = "" if existing == target else f" ({existing} cannot be written)"
        raise InputError(f"output directory cannot be written{where}", path=path)
    if swapped and existing == target and not os.access(target.parent, os.W_OK | os.X_OK):
        raise InputError(f"output directory cannot be replaced: {target.parent} cannot be written "
                         "(a run is staged beside its output directory and renamed into place)", path=path)
    return target


def check_out(out: OutputDir, inputs: Sequence[Path | None] = (), listed: bool = True) -> OutputDir:
    """``out`` resolved if a publication may replace it: usable, holding no
    input of the run, and (unless ``out.replace``) nothing but what a rotcal
    listing names (``listed``: the listing counts; a simulated dataset has
    none, so any file there is foreign). Raises ``InputError``."""
    target = usable(out.path)
    for given in (Path(p).resolve() for p in inputs if p is not None):
        if target == given or target in given.parents:
            raise InputError(f"output directory holds the input {given}: a run replaces its whole output directory",
                             path=out.path)
    if not out.replace and target.is_dir():
        foreign = next(foreign_files(target, listed), None)
        if foreign is not None:
            problem = "holds files no rotcal listing names" if listed else "is not empty"
            raise InputError(f"output directory {problem} (e.g. {foreign})", path=out.path, hint="--replace replaces them")
    return OutputDir(target, out.replace, out.on_table)


def foreign_files(directory: Path, listed: bool = True) -> Iterator[str]:
    """What in ``directory`` (relative names) no listing there names with its
    size and SHA-256: files changed since rotcal wrote them, files it did
    not write, links, empty or unreadable folders. A generator: a refusal
    needs only the first."""
    owned = _listed(directory) if listed else {}
    unreadable: list[OSError] = []  # folders os.walk could not list: what they hold cannot be known
    for root, folders, files in os.walk(directory, onerror=unreadable.append):
        here = Path(root)
        folders.sort()
        yield from (Path(error.filename).relative_to(directory).as_posix() for error in unreadable)
        unreadable.clear()
        if here != directory and not folders and not files:
            yield here.relative_to(directory).as_posix()
        for path in [*(here / f for f in folders if (here / f).is_symlink()), *(here / f for f in sorted(files))]:
            name = path.relative_to(directory).as_posix()
            if not (name == LISTING and owned) and not _unchanged(path, owned.get(name)):
                yield name
    yield from (Path(error.filename).relative_to(directory).as_posix() for error in unreadable)


def _listed(directory: Path) -> dict[str, tuple[int, str]]:
    """(size, SHA-256) of every file the listing in ``directory`` names; {} without a valid listing."""
    path = directory / LISTING
    try:
        doc = json.loads(path.read_text()) if path.is_file() and not path.is_symlink() else {}
        if (doc.get("schema"), doc.get("schema_version")) != LISTING_SCHEMA:
            return {}
        return {f["name"]: (int(f["bytes"]), str(f["sha256"])) for f in doc["files"]}
    except (OSError, ValueError, TypeError, KeyError, AttributeError):
        return {}


def _unchanged(path: Path, recorded: tuple[int, str] | None) -> bool:
    """Whether ``path`` is a regular file with the size and SHA-256 a listing recorded (the hash read only when the size agrees)."""
    if recorded is None or path.is_symlink() or not path.is_file() or path.stat().st_size != recorded[0]:
        return False
    from rotcal.ingest.duplicates import sha256_hex  # here: the CLI checks --out before it loads the stages

    return sha256_hex(path) == recorded[1]


def listing(directory: Path) -> dict:
    """The listing of every file under ``directory`` (``schemas/rotcal_files.json``)."""
    from rotcal.ingest.duplicates import sha256_hex
    from rotcal.model.calibration import created_utc  # the run's one time, SOURCE_DATE_EPOCH honoured

    files = sorted((path.relative_to(directory).as_posix(), path) for path in directory.rglob("*") if path.is_file())
    entries = [{"name": name, "bytes": path.stat().st_size, "sha256": sha256_hex(path)} for name, path in files]
    return {"schema": LISTING_SCHEMA[0], "schema_version": LISTING_SCHEMA[1], "rotcal_version": __version__,
            "run_time": created_utc(), "files": entries}


def publish_directory(out: OutputDir, write: Callable[[Path], Sequence[Path]], listed: bool = True) -> tuple[Path, ...]:
    """Publish what ``write`` writes into an empty directory as the whole of
    ``out.path``: staged beside it, listed (``listed``), swapped in. Returns
    the published paths ``write`` returned (then the listing). A failure
    while writing leaves the old output as it was. Raises ``InputError``
    when ``out`` cannot be replaced (``check_out``)."""
    target = check_out(out, listed=listed).path
    target.parent.mkdir(parents=True, exist_ok=True)
    remove_leftovers(target)
    staging = _beside(target, "staging")
    staging.mkdir()
    try:
        written = list(write(staging))
        if listed:
            doc = listing(staging)
            (staging / LISTING).write_text(json_text(doc))
            written.append(staging / LISTING)
        _swap(staging, target)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return tuple(target / path.relative_to(staging) for path in written)


def _beside(target: Path, kind: str) -> Path:
    """A temporary directory's name beside ``target``: hidden, naming the target, this process and a random token."""
    return target.with_name(f".{target.name}.rotcal-{kind}.{os.getpid()}.{uuid.uuid4().hex[:8]}")


def remove_leftovers(target: Path) -> list[Path]:
    """Remove the staging and aside directories of ``target`` left by
    publications whose process is gone (killed mid-run); the paths removed."""
    pattern = re.compile(rf"\.{re.escape(target.name)}\.rotcal-(?:{'|'.join(_KINDS)})\.(\d+)\.[0-9a-f]{{8}}")
    removed = []
    for path in target.parent.iterdir():
        match = pattern.fullmatch(path.name)
        if match and path.is_dir() and not path.is_symlink() and not _alive(int(match.group(1))):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed


def _alive(pid: int) -> bool:
    """Whether process ``pid`` runs (signal 0 checks without sending, kill(2))."""
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # no such process; a number beyond any pid
        return False
    except PermissionError:  # another user's
        return True
    return True


def _swap(staging: Path, target: Path) -> None:
    """Rename ``target`` aside, ``staging`` into its place, then remove the old
    one: each rename atomic, so ``target`` is whole at every moment but the
    one between the two renames."""
    try:
        if not target.exists():
            os.rename(staging, target)
            return
        shutil.copymode(target, staging)  # the permissions a user gave the directory stay
        aside = _beside(target, "old")
        os.rename(target, aside)
        try:
            os.rename(staging, target)
        except OSError:
            os.rename(aside, target)
            raise
    except OSError as exc:
        raise InputError(f"output directory cannot be replaced: {exc.strerror}", path=target) from None
    shutil.rmtree(aside, ignore_errors=True)
