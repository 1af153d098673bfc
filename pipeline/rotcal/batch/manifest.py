"""A batch run's output directory DIR and its bookkeeping: the run manifest
(SQLite: per dataset its input hashes, configuration, version, status,
reason and timings), the cache of input content hashes, the lock that stops
two runs from overlapping, and the layout results are published in.

DIR holds
    manifest.sqlite     the run manifest (``Manifest``)
    batch.lock          the run lock (``run_lock``)
    datasets/<id>       link to one dataset's tables, replaced atomically
    combined            link to the combined dataset: combined/<table>/<id>.parquet
    .store/             what the links point to; nothing else is kept there
    .work/              jobs' and builds' temporary folders, emptied at every start and end

Folders are written under ``.work`` and renamed into ``.store``; links are
swapped with ``rename``, so a reader, or a run killed at any moment, sees a
dataset's old tables or its new ones, never a mixture. The SQLite tables
are created from their contracts in ``schemas/`` (``batch_datasets``,
``batch_runs``, ``batch_file_hashes``).
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import socket
import sqlite3
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields
from datetime import UTC, datetime
from pathlib import Path

from rotcal.errors import ExitCode, RotcalError
from rotcal.ingest.duplicates import file_identity
from rotcal.ingest.files import open_capture
from rotcal_schemas import schema_text

MANIFEST_VERSION = 1
_SQL_TYPES = {"string": "TEXT", "float64": "REAL", "int64": "INTEGER"}
# A file changed within this long before it was hashed may change again
# within one time-stamp tick without its ctime moving: hash it again next time.
RACY_NS = 2_000_000_000


def now() -> str:
    """The time stamps of the manifest and the batch summary: UTC, milliseconds."""
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


class LockedError(RotcalError):
    """Another batch run holds the output directory's lock."""

    exit_code = ExitCode.LOCKED


@dataclass(frozen=True)
class DatasetRecord:
    """One row of ``batch_datasets`` (see its schema for the columns)."""

    dataset_path: str
    dataset_id: str
    status: str
    fingerprint: str
    inputs: str
    config: str
    rotcal_version: str
    reason: str | None
    output: str | None
    tables: str
    run_id: str
    started_at: str
    finished_at: str
    duration_s: float


def _create_table(db: sqlite3.Connection, name: str) -> None:
    """The table of contract ``name``, with the columns a later version of
    the contract added appended to a table an earlier rotcal made."""
    doc = schema_text(name)
    columns = ", ".join(f"{c['name']} {_SQL_TYPES[c['type']]}" for c in doc["columns"])
    db.execute(f"CREATE TABLE IF NOT EXISTS {name} ({columns}, PRIMARY KEY ({doc['primary_key']}))")
    have = {row[1] for row in db.execute(f"PRAGMA table_info({name})")}
    for column in doc["columns"]:
        if column["name"] not in have:
            db.execute(f"ALTER TABLE {name} ADD COLUMN {column['name']} {_SQL_TYPES[column['type']]}")


class Manifest:
    """The SQLite manifest of one output directory. Every write is its own
    transaction, so a run killed at any moment leaves it consistent."""

    def __init__(self, path: Path):
        self.path = path
        self.db = sqlite3.connect(path, isolation_level=None)
        try:
            # Each commit reaches the OS before it returns (a killed run loses
            # none); only a power cut could lose the last ones, then redone.
            self.db.execute("PRAGMA synchronous = NORMAL")
            version = self.db.execute("PRAGMA user_version").fetchone()[0]
            if version not in (0, MANIFEST_VERSION):
                raise RotcalError(f"manifest format {version} is not {MANIFEST_VERSION}: written by another rotcal", path=path)
            with self.transaction():
                for name in ("batch_datasets", "batch_runs", "batch_file_hashes"):
                    _create_table(self.db, name)
                self.db.execute(f"PRAGMA user_version = {MANIFEST_VERSION}")
        except sqlite3.DatabaseError as exc:
            self.db.close()
            raise RotcalError(f"the manifest cannot be read: {exc}", path=path,
                              hint="move it away: the next run then processes every dataset again") from None

    def close(self) -> None:
        self.db.close()

    @contextmanager
    def transaction(self) -> Iterator[None]:
        self.db.execute("BEGIN IMMEDIATE")
        try:
            yield
        except BaseException:
            self.db.execute("ROLLBACK")
            raise
        self.db.execute("COMMIT")

    def records(self) -> dict[str, DatasetRecord]:
        names = [f.name for f in fields(DatasetRecord)]
        rows = self.db.execute(f"SELECT {', '.join(names)} FROM batch_datasets")
        return {row[0]: DatasetRecord(*row) for row in rows}

    def put(self, record: DatasetRecord) -> None:
        names = [f.name for f in fields(DatasetRecord)]
        with self.transaction():
            self.db.execute(
                f"INSERT OR REPLACE INTO batch_datasets ({', '.join(names)}) VALUES ({', '.join('?' * len(names))})",
                [getattr(record, n) for n in names],
            )

    def start_run(self, run_id: str, started_at: str, root: str, executor: str, workers: int, version: str) -> list[str]:
        """Record a run as running; the runs that never finished (killed:
        this run holds the lock, so none is live) are marked interrupted and
        returned."""
        with self.transaction():
            dead = [row[0] for row in self.db.execute(
                "SELECT run_id FROM batch_runs WHERE finished_at IS NULL AND (status IS NULL OR status = 'running') "
                "ORDER BY run_id")]
            self.db.execute("UPDATE batch_runs SET status = 'interrupted' WHERE finished_at IS NULL")
            self.db.execute(
                "INSERT INTO batch_runs (run_id, started_at, root, executor, workers, rotcal_version, status) "
                "VALUES (?, ?, ?, ?, ?, ?, 'running')",
                (run_id, started_at, root, executor, workers, version),
            )
        return dead

    def finish_run(self, run_id: str, finished_at: str, summary_json: str) -> None:
        with self.transaction():
            self.db.execute("UPDATE batch_runs SET finished_at = ?, summary = ?, status = 'finished' WHERE run_id = ?",
                            (finished_at, summary_json, run_id))

    def digest(self, path: Path) -> tuple[str, tuple[int, ...] | None]:
        """SHA-256 of ``path``'s content, read in blocks (bounded memory) unless
        the cache holds it for the same device, inode, size, mtime and ctime
        (``file_identity``); and that identity when it vouches for the
        content (the file last changed more than ``RACY_NS`` before it was
        hashed), else None."""
        st = path.stat()
        key = str(path)
        identity = file_identity(st)
        row = self.db.execute(
            "SELECT device, inode, size, mtime_ns, ctime_ns, sha256, hashed_at_ns FROM batch_file_hashes WHERE path = ?", (key,)
        ).fetchone()
        if row is not None and row[:5] == identity and st.st_ctime_ns < row[6] - RACY_NS:
            return row[5], identity
        hashed_at = time.time_ns()
        # open_capture: a FIFO would block the run for ever, holding the lock
        with open_capture(path) as fh:
            sha = hashlib.file_digest(fh, "sha256").hexdigest()
        self.db.execute("INSERT OR REPLACE INTO batch_file_hashes VALUES (?, ?, ?, ?, ?, ?, ?, ?)", (key, *identity, sha, hashed_at))
        return sha, identity if st.st_ctime_ns < hashed_at - RACY_NS else None


@contextmanager
def run_lock(out: Path) -> Iterator[str | None]:
    """Hold ``out/batch.lock`` for a run; yields what a dead run left in it.

    The lock is an ``flock`` the kernel drops when its holder dies, so a lock
    left by a killed run is stale by construction: the file still names that
    run (a clean run empties it on exit), which is reported, and taken over.
    Raises ``LockedError`` naming the holder when a live run has it.
    """
    path = out / "batch.lock"
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode(errors="replace").strip() or "another process"
            raise LockedError(f"another batch run holds the lock ({holder})", path=path,
                              hint="runs must not overlap: schedule them further apart") from None
        stale = os.pread(fd, 4096, 0).decode(errors="replace").strip() or None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()} since {time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime())}\n".encode(), 0)
        try:
            yield stale
        finally:  # a run that ends, even with an error, is not a dead run
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)


class Layout:
    """DIR's folders, and the only code that changes them (see the module doc)."""

    def __init__(self, out: Path):
        self.out, self.datasets, self.store, self.work = out, out / "datasets", out / ".store", out / ".work"
        for folder in (self.datasets, self.store, self.work):
            folder.mkdir(parents=True, exist_ok=True)

    def _link(self, link: Path, target: str) -> None:
        tmp = link.with_name(f".{link.name}.{os.getpid()}.tmp")
        tmp.unlink(missing_ok=True)
        os.symlink(target, tmp)
        os.replace(tmp, link)

    def _trash(self, path: Path) -> None:
        """Remove a folder atomically as far as readers see: rename, then delete."""
        doomed = self.work / f"trash.{uuid.uuid4().hex}"
        os.rename(path, doomed)
        shutil.rmtree(doomed)

    def published(self, dataset_id: str) -> str | None:
        """The ``.store`` folder ``datasets/<dataset_id>`` points to."""
        try:
            target = Path(os.readlink(self.datasets / dataset_id))
        except (FileNotFoundError, OSError):
            return None
        return target.parent.name if (self.store / target.parent.name).is_dir() else None

    def publish(self, dataset_id: str, fingerprint: str, work: Path) -> str:
        """Move a finished job's folder into the store and point the dataset's link at it."""
        name = f"{dataset_id}.{fingerprint[:16]}"
        if (self.store / name).is_dir():  # the same inputs, published before a crash
            shutil.rmtree(work)
        else:
            os.rename(work, self.store / name)
        self._link(self.datasets / dataset_id, f"../.store/{name}/tables")
        return name

    def withdraw(self, dataset_id: str) -> None:
        (self.datasets / dataset_id).unlink(missing_ok=True)

    def publish_combined(self, published: dict[str, str]) -> Path:
        """``combined/<table>/<dataset_id>.parquet`` for every published dataset
        (hard links to the stored parts), built aside and swapped in whole."""
        signature = hashlib.sha256(json.dumps(sorted(published.items())).encode()).hexdigest()[:16]
        name = f"combined.{signature}"
        if not (self.store / name).is_dir():
            build = self.work / name
            build.mkdir()
            tables: set[str] = set()  # each table's folder made once
            for did, stored in sorted(published.items()):
                for part in sorted((self.store / stored / "parts").glob("*.parquet")):
                    if part.stem not in tables:
                        (build / part.stem).mkdir()
                        tables.add(part.stem)
                    try:
                        os.link(part, build / part.stem / f"{did}.parquet")
                    except OSError:  # a file system without hard links
                        shutil.copyfile(part, build / part.stem / f"{did}.parquet")
            os.rename(build, self.store / name)
        link = self.out / "combined"
        if not link.is_symlink() or os.readlink(link) != f".store/{name}":
            self._link(link, f".store/{name}")
        return link

    def sweep(self) -> None:
        """Delete what a killed run left: job folders, half-made links, and
        stored folders no link points to."""
        for path in self.work.iterdir():
            if path.is_dir() and not path.is_symlink():
                shutil.rmtree(path)
            else:
                path.unlink()
        live = set()
        for link in self.datasets.iterdir():
            stored = self.published(link.name)
            if link.name.startswith(".") or stored is None:
                link.unlink()
            else:
                live.add(stored)
        combined = self.out / "combined"
        if combined.is_symlink():
            live.add(Path(os.readlink(combined)).name)
        for path in self.store.iterdir():
            if path.name not in live:
                self._trash(path)
