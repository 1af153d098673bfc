"""``rotcal batch``: every new or changed dataset under ROOT through
``run.run_dataset``, on a local process pool or a Dask cluster, with results
published atomically into DIR (``manifest.Layout``) and a manifest saying
what was done (``manifest.Manifest``). Batch holds no pipeline logic.

A dataset is re-processed when the SHA-256 of any input, the configuration
or the rotcal version changes (its fingerprint); docs/batch.md has the rules.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import multiprocessing
import os
import re
import shutil
import signal
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from rotcal import __version__
from rotcal.batch.manifest import DatasetRecord, Layout, Manifest, run_lock
from rotcal.config import BatchConfig, Limits, RunConfig
from rotcal.errors import ConfigError, InputError, LimitError, RotcalError
from rotcal.ingest import CAPTURE_SUFFIXES, capture_files
from rotcal.ingest.meta import load_meta

EXIT_QUARANTINE = 4
_CLEAN_PART = re.compile(r"[A-Za-z0-9.-]+(?:_[A-Za-z0-9.-]+)*")
_EXECUTOR = re.compile(r"local|dask://([^/\s]+:[0-9]+)")


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


# -- what the datasets are ----------------------------------------------------

@dataclass(frozen=True)
class Found:
    """A dataset under ROOT: its path relative to ROOT (bytes that are not
    UTF-8 shown as ``\\xNN``) and where it is."""

    dataset_path: str
    source: Path


def _printable(text: str) -> str:
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def dataset_id(dataset_path: str) -> str:
    """A unique, file-system-safe name for ``dataset_path``.

    Paths made of plain names read as themselves with ``/`` written ``__``
    (``lab1/DUT-7`` -> ``lab1__DUT-7``); plain names hold no ``__`` and do not
    start or end with ``_``, so this is reversible. Any other path becomes a
    slug and a hash of the path, marked by ``~``, which plain names never
    hold: no two paths share a name.
    """
    parts = dataset_path.split("/")
    name = "__".join(parts)
    if all(_CLEAN_PART.fullmatch(p) and not p.startswith(".") for p in parts) and len(name) <= 120:
        return name
    slug = re.sub(r"[^A-Za-z0-9.-]+", "_", dataset_path)[:80].lstrip(".")
    return f"{slug}~{hashlib.sha256(dataset_path.encode()).hexdigest()[:16]}"


def discover(root: Path, out: Path) -> list[Found]:
    """Every dataset under ``root``, by path.

    A directory holding ``dataset.toml`` is one dataset (not searched
    further); elsewhere each capture file is a dataset of its own, and
    subdirectories are searched. Hidden entries and ``out`` are skipped;
    directory links are not followed (each is reported as a dataset, which
    ``dataset_inputs`` refuses).
    """
    found, stack = [], [root]
    while stack:
        directory = stack.pop()
        with os.scandir(directory) as it:
            entries = [e for e in it if not e.name.startswith(".")]
        for entry in entries:
            path = Path(entry.path)
            rel = _printable(path.relative_to(root).as_posix())
            if entry.is_dir(follow_symlinks=False):
                if path == out:
                    continue
                if (path / "dataset.toml").is_file() or (path / "dataset.toml").is_symlink():
                    found.append(Found(rel, path))
                else:
                    stack.append(path)
            elif entry.is_symlink() and path.is_dir():
                found.append(Found(rel, path))
            elif path.suffix.lower() in CAPTURE_SUFFIXES:
                found.append(Found(rel, path))
    return sorted(found, key=lambda f: f.dataset_path)


def _confined(file: Path, home: Path) -> None:
    if not file.resolve().is_relative_to(home):
        raise InputError(f"{file.name!r} is a symbolic link pointing outside the dataset directory", path=file)


def dataset_inputs(source: Path, limits: Limits) -> list[Path]:
    """The files the pipeline reads for a dataset (``dataset.toml`` first),
    each checked to resolve inside the dataset's directory, before anything
    is read but ``dataset.toml`` (itself refused above
    ``limits.max_dataset_toml_bytes``).

    Raises ``InputError`` (``LimitError``) with the reason.
    """
    if source.is_symlink() and source.is_dir():
        raise InputError("a symbolic link to a directory: rotcal batch does not follow directory links", path=source)
    if not source.is_dir():
        _confined(source, source.parent.resolve())
        return [source]
    home = source.resolve()
    toml = source / "dataset.toml"
    _confined(toml, home)
    if toml.stat().st_size > limits.max_dataset_toml_bytes:
        raise LimitError(f"dataset.toml is larger than the limit of {limits.max_dataset_toml_bytes} bytes", path=toml)
    files = [toml] + [file for file, _ in capture_files(source, load_meta(toml))]
    for file in files:
        _confined(file, home)
    return files


def _listing(source: Path) -> list[list]:
    """Names, sizes, times and link targets under a refused dataset (no
    content read): its refusal is reconsidered when any of them changes."""
    if not source.is_dir() or source.is_symlink():
        st = source.lstat()
        return [[source.name, st.st_size, st.st_mtime_ns, os.readlink(source) if source.is_symlink() else None]]
    rows = []
    for directory, dirs, files in os.walk(source):
        for name in sorted(dirs + files):
            path = Path(directory, name)
            st = path.lstat()
            rows.append([path.relative_to(source).as_posix(), st.st_size, st.st_mtime_ns,
                         os.readlink(path) if path.is_symlink() else None])
    return sorted(rows)


def config_json(config: RunConfig) -> str:
    """The configuration results depend on: every section but worker counts,
    executors and where it was read from."""
    doc = asdict(config)
    for key in ("workers", "batch", "source"):
        doc.pop(key)
    return json.dumps(doc, sort_keys=True)


@dataclass(frozen=True)
class Plan:
    """A dataset's identity this run: inputs and fingerprint, or why it is refused."""

    found: Found
    dataset_id: str
    fingerprint: str
    inputs: str
    refusal: str | None


def plan_dataset(found: Found, root: Path, config: RunConfig, manifest: Manifest) -> Plan:
    """Hash the dataset's inputs (``manifest.digest``), or say why it is refused."""
    try:
        if found.dataset_path != found.source.relative_to(root).as_posix():
            raise InputError("the path is not valid UTF-8 (rename it)", path=found.dataset_path)
        files = dataset_inputs(found.source, config.limits)
        inputs = [[_printable(f.relative_to(root).as_posix()), manifest.digest(f)] for f in files]
        refusal = None
    except (RotcalError, OSError) as exc:  # OSError: unreadable, or gone since it was found
        refusal = str(exc) if isinstance(exc, RotcalError) else \
            str(InputError(f"cannot be read: {exc.strerror or exc}", path=_printable(str(exc.filename or found.source))))
        try:
            inputs = [["listing", _listing(found.source)]]
        except OSError:
            inputs = [["listing", None]]
    identity = {"dataset": found.dataset_path, "inputs": inputs, "config": config_json(config), "rotcal": __version__}
    fingerprint = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
    return Plan(found, dataset_id(found.dataset_path), fingerprint, json.dumps(inputs), refusal)


# -- one job, on a worker -------------------------------------------------------

@dataclass(frozen=True)
class Job:
    dataset_path: str
    source: str
    work: str
    config: RunConfig


@dataclass(frozen=True)
class JobResult:
    status: str  # ok, quarantined or error
    reason: str | None
    tables: tuple[str, ...]
    started_at: str
    duration_s: float
    rotcal_version: str = __version__


def _write_part(table_path: Path, part_path: Path, dataset_path: str) -> None:
    """The table with ``dataset_path`` in front (contract ``batch_combined``)."""
    table = pq.read_table(table_path)
    table = table.add_column(0, pa.field("dataset_path", pa.string()), pa.array([dataset_path] * table.num_rows, pa.string()))
    table = table.replace_schema_metadata({**(table.schema.metadata or {}), b"rotcal.combined": b"batch_combined 1.0"})
    part_path.parent.mkdir(parents=True, exist_ok=True)
    pq.write_table(table, part_path, compression="zstd")


def run_job(job: Job) -> JobResult:
    """One dataset into ``job.work`` (``tables/`` and ``parts/``), on whatever
    worker runs it; the folder is removed unless the result is ok."""
    from rotcal.run import run_dataset  # the stages (scipy, the diagnosis) load on workers only

    started, clock = _now(), time.perf_counter()
    work = Path(job.work)
    try:
        dataset_inputs(Path(job.source), job.config.limits)  # again: the worker reads the files now
        outcome = run_dataset(Path(job.source), work / "tables", None, job.config)
        tables = [path for path in outcome.written if path.suffix == ".parquet"]  # not the report and its figures
        for path in tables:
            _write_part(path, work / "parts" / path.name, job.dataset_path)
        return JobResult("ok", None, tuple(p.stem for p in tables), started, time.perf_counter() - clock)
    except RotcalError as exc:
        status, reason = "quarantined", str(exc)
    except Exception as exc:  # a bug or the machine, not the data: retried on the next run
        status, reason = "error", f"unexpected {type(exc).__name__} (a bug: please report it): {exc}"
    shutil.rmtree(work, ignore_errors=True)
    return JobResult(status, " ".join(reason.split()), (), started, time.perf_counter() - clock)


# -- executors --------------------------------------------------------------------

def _die_with_parent(parent_pid: int) -> None:
    """Pool worker start: end with the batch process (SIGKILL included), so
    no orphan goes on writing after it; leave Ctrl-C to the batch process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:
        os._exit(1)


class _InProcess(Executor):
    """One worker: jobs run in this process, at submission."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except Exception as exc:
            future.set_exception(exc)
        return future


class _LocalPool(Executor):
    """Worker processes (spawned: no forked library state); a pool broken by
    a worker's death is replaced, and the jobs it held fail as errors."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = self._new()

    def _new(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_die_with_parent, initargs=(os.getpid(),))

    def submit(self, fn, /, *args, **kwargs) -> Future:
        try:
            return self.pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = self._new()
            return self.pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.pool.shutdown(wait=wait, cancel_futures=cancel_futures)


def _cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def check_executor(spec: str) -> str:
    """``local`` or ``dask://HOST:PORT``; raises ``ConfigError`` otherwise."""
    if not _EXECUTOR.fullmatch(spec):
        raise ConfigError(f"executor {spec!r} is not 'local' or 'dask://HOST:PORT'")
    return spec


@contextmanager
def open_executor(batch: BatchConfig, jobs: int) -> Iterator[tuple[Executor, int]]:
    """The executor of ``batch.executor`` and how many jobs it runs at once."""
    match = _EXECUTOR.fullmatch(check_executor(batch.executor))
    if match.group(1) is None:
        workers = min(batch.workers or _cores(), jobs)
        executor = _InProcess() if workers == 1 else _LocalPool(workers)
        with executor:
            yield executor, workers
        return
    try:
        from distributed import Client
    except ImportError:
        raise ConfigError("the dask executor needs the distributed package (pip install 'rotcal[dask]')") from None
    address = f"tcp://{match.group(1)}"
    try:
        client = Client(address, timeout="10s")
    except (OSError, TimeoutError) as exc:
        raise ConfigError(f"cannot reach the Dask scheduler at {address}: {exc}") from None
    with client:
        yield client.get_executor(pure=False), max(1, sum(client.nthreads().values()))


def _execute(executor: Executor, workers: int, jobs: list[tuple[Plan, Job]]) -> Iterator[tuple[Plan, JobResult]]:
    """Results as jobs finish, with at most two per worker submitted at a time."""
    queue, running = deque(jobs), {}
    while queue or running:
        while queue and len(running) < 2 * workers:
            plan, job = queue.popleft()
            running[executor.submit(run_job, job)] = plan
        done, _ = wait(running, return_when=FIRST_COMPLETED)
        for future in sorted(done, key=lambda f: running[f].found.dataset_path):
            plan = running.pop(future)
            try:
                result = future.result()
            except Exception as exc:  # the worker died (killed, crashed, out of memory) or the cluster failed
                result = JobResult("error", " ".join(f"the worker failed: {type(exc).__name__}: {exc}".split()), (), _now(), 0.0)
            yield plan, result


# -- progress -----------------------------------------------------------------------

class Reporter:
    """A batch run's progress on ``console``: a rich progress bar with a line
    per dataset on a terminal, plain time-stamped log lines otherwise; nothing
    without a console."""

    def __init__(self, console: Console | None = None):
        self.console, self.progress, self.done, self.total = console, None, 0, 0

    def __enter__(self) -> Reporter:
        return self

    def __exit__(self, *exc) -> None:
        if self.progress is not None:
            self.progress.stop()

    def _print(self, text: str, style: str = "") -> None:
        if self.progress is not None:
            self.progress.console.print(text, style=style, highlight=False, markup=False, soft_wrap=True)
        elif self.console is not None:
            self.console.print(f"{_now()} rotcal batch: {text}", highlight=False, markup=False, soft_wrap=True)

    def note(self, text: str) -> None:
        self._print(text)

    def start(self, discovered: int, unchanged: int, total: int) -> None:
        self.total = total
        self.note(f"{discovered} datasets found: {unchanged} unchanged, {total} to process")
        if self.console is not None and self.console.is_terminal and total:
            self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), TimeRemainingColumn(), console=self.console)
            self.progress.start()
            self.task = self.progress.add_task("rotcal batch", total=total)

    def dataset(self, dataset_path: str, result: JobResult) -> None:
        self.done += 1
        text = f"[{self.done}/{self.total}] {result.status} {dataset_path} ({result.duration_s:.2f} s)"
        self._print(text + (f": {result.reason}" if result.reason else ""),
                    {"ok": "green", "quarantined": "yellow"}.get(result.status, "red"))
        if self.progress is not None:
            self.progress.update(self.task, advance=1, description=f"{result.status} {dataset_path}")


# -- the run --------------------------------------------------------------------------

@dataclass(frozen=True)
class BatchSummary:
    """What a run did (``schemas/batch_summary.json``)."""

    run_id: str
    root: str
    out: str
    executor: str
    workers: int
    rotcal_version: str
    discovered: int
    unchanged: int
    processed: int
    ok: int
    quarantined: int
    errors: int
    still_quarantined: int
    not_found: int
    problems: tuple[dict, ...]
    combined: str
    wall_s: float
    notes: tuple[str, ...]

    @property
    def exit_status(self) -> int:
        """0 all published; 4 a dataset is in quarantine (new or unchanged);
        1 a dataset failed unexpectedly (retried next run)."""
        if self.errors:
            return 1
        return EXIT_QUARANTINE if self.quarantined or self.still_quarantined else 0

    def as_dict(self) -> dict:
        return {**asdict(self), "problems": list(self.problems), "notes": list(self.notes), "exit_status": self.exit_status}

    def text(self) -> str:
        lines = [f"{self.discovered} datasets: {self.processed} processed ({self.ok} ok, {self.quarantined} quarantined, "
                 f"{self.errors} errors), {self.unchanged} unchanged ({self.still_quarantined} still quarantined); "
                 f"{self.wall_s:.1f} s"]
        lines += [f"{p['status']}: {p['dataset_path']}: {p['reason']}" for p in self.problems]
        lines.append(f"combined dataset: {self.combined}")
        return "\n".join(lines)


def _checked_dirs(root: Path, out: Path) -> tuple[Path, Path]:
    root, out = Path(root).resolve(), Path(out).resolve()
    if not root.is_dir():
        raise InputError("ROOT is not a directory", path=root)
    if (root / "dataset.toml").exists():
        raise InputError("ROOT is itself a dataset (it holds dataset.toml)", path=root,
                         hint="give the folder that holds the datasets, or use rotcal run")
    if root == out or root.is_relative_to(out):
        raise InputError("ROOT must not be the output directory or inside it", path=root)
    out.mkdir(parents=True, exist_ok=True)
    return root, out


def run_batch(root: Path, out: Path, config: RunConfig = RunConfig(), reporter: Reporter | None = None) -> BatchSummary:
    """Process every new or changed dataset under ``root`` into ``out``.

    Raises ``InputError`` for a bad ROOT, ``ConfigError`` for a bad executor,
    ``manifest.LockedError`` when another run holds ``out``'s lock. Bad
    datasets do not raise: they are quarantined with their reason.
    """
    check_executor(config.batch.executor)
    root, out = _checked_dirs(root, out)
    reporter = reporter or Reporter()
    clock = time.perf_counter()
    with run_lock(out) as stale:
        notes = (f"took over the stale lock of a run that died ({stale})",) if stale else ()
        for note in notes:
            reporter.note(note)
        manifest = Manifest(out / "manifest.sqlite")
        try:
            return _run(root, out, config, manifest, reporter, clock, notes)
        finally:
            manifest.close()


def _run(root: Path, out: Path, config: RunConfig, manifest: Manifest, reporter: Reporter, clock: float,
         notes: tuple[str, ...]) -> BatchSummary:
    layout = Layout(out)
    layout.sweep()
    run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S.%fZ}-{os.getpid()}"
    previous = manifest.records()
    with manifest.transaction():
        plans = [plan_dataset(found, root, config, manifest) for found in discover(root, out)]
    todo, refused, unchanged = [], [], []
    for plan in plans:
        prev = previous.get(plan.found.dataset_path)
        current = prev is not None and prev.fingerprint == plan.fingerprint and (
            prev.status == "quarantined" or (prev.status == "ok" and layout.published(plan.dataset_id) == prev.output))
        (unchanged if current else refused if plan.refusal else todo).append(plan)
    local, workers = config.batch.executor == "local", 0
    manifest.start_run(run_id, _now(), str(root), config.batch.executor, config.batch.workers, __version__)
    reporter.start(len(plans), len(unchanged), len(todo) + len(refused))
    outcomes: list[tuple[Plan, JobResult]] = []

    def settle(plan: Plan, result: JobResult, work: Path | None) -> None:
        if result.status == "ok" and result.rotcal_version != __version__:
            result = replace(result, status="error", reason=f"the worker runs rotcal {result.rotcal_version}, this run {__version__}")
        output = None
        if result.status == "ok":
            output = layout.publish(plan.dataset_id, plan.fingerprint, work)
        else:
            layout.withdraw(plan.dataset_id)
            if work is not None:
                shutil.rmtree(work, ignore_errors=True)
        if result.reason is not None:
            result = replace(result, reason=_printable(result.reason))
        manifest.put(DatasetRecord(
            plan.found.dataset_path, plan.dataset_id, result.status, plan.fingerprint, plan.inputs, config_json(config),
            __version__, result.reason, output, json.dumps(result.tables), run_id, result.started_at, _now(), result.duration_s))
        outcomes.append((plan, result))
        reporter.dataset(plan.found.dataset_path, result)

    for plan in refused:
        settle(plan, JobResult("quarantined", plan.refusal, (), _now(), 0.0), None)
    if todo:
        with open_executor(config.batch, len(todo)) as (executor, workers):
            # One fit thread per job when jobs run side by side; results do not depend on it.
            job_config = replace(config, workers=config.workers if workers == 1 and local else 1)
            jobs = [(plan, Job(plan.found.dataset_path, str(plan.found.source),
                               str(layout.work / f"{plan.dataset_id}.{run_id}"), job_config)) for plan in todo]
            for plan, result in _execute(executor, workers, jobs):
                settle(plan, result, layout.work / f"{plan.dataset_id}.{run_id}")
    records = manifest.records()
    combined = layout.publish_combined({r.dataset_id: r.output for r in records.values()
                                        if r.status == "ok" and layout.published(r.dataset_id) == r.output})
    layout.sweep()
    seen = {p.found.dataset_path for p in plans}
    problems = [{"dataset_path": p.found.dataset_path, "status": r.status, "reason": r.reason}
                for p, r in outcomes if r.status != "ok"]
    problems += [{"dataset_path": p.found.dataset_path, "status": "quarantined", "reason": previous[p.found.dataset_path].reason}
                 for p in unchanged if previous[p.found.dataset_path].status == "quarantined"]
    count = {s: sum(r.status == s for _, r in outcomes) for s in ("ok", "quarantined", "error")}
    summary = BatchSummary(
        run_id=run_id, root=str(root), out=str(out), executor=config.batch.executor, workers=workers,
        rotcal_version=__version__, discovered=len(plans), unchanged=len(unchanged), processed=len(outcomes),
        ok=count["ok"], quarantined=count["quarantined"], errors=count["error"],
        still_quarantined=sum(previous[p.found.dataset_path].status == "quarantined" for p in unchanged),
        not_found=sum(key not in seen for key in records), problems=tuple(problems), combined=str(combined),
        wall_s=round(time.perf_counter() - clock, 3), notes=notes,
    )
    manifest.finish_run(run_id, _now(), json.dumps(summary.as_dict()))
    return summary
