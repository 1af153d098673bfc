"""``rotcal batch``, second step: each dataset's job (``run.run_dataset``
into a work folder) and the executors that run jobs: in this process, on a
local process pool, or on a Dask cluster.
"""

from __future__ import annotations

import ctypes
import importlib
import multiprocessing
import os
import shutil
import signal
import sys
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import FIRST_COMPLETED, Executor, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import rotcal
from rotcal import __version__
from rotcal.batch.manifest import now
from rotcal.batch.plan import Plan, dataset_inputs
from rotcal.config import EXECUTOR, BatchConfig, RunConfig
from rotcal.errors import ConfigError, RotcalError
from rotcal.parallel import cores, share
from rotcal.report.publish import OutputDir

if TYPE_CHECKING:
    import pyarrow as pa

# -- one job, on a worker -------------------------------------------------------

@dataclass(frozen=True)
class Job:
    dataset_path: str
    source: str
    work: str
    config: RunConfig
    known: dict[tuple[int, ...], str]  # the inputs' SHA-256s the batch process computed (``Plan.known``)


@dataclass(frozen=True)
class JobResult:
    status: str  # ok, quarantined or error
    reason: str | None
    tables: tuple[str, ...]
    started_at: str
    duration_s: float
    rotcal_version: str = __version__
    findings: tuple[str, ...] = ()  # the diagnosis's detected effects (``unexplained`` included), in its order


def _write_part(table: pa.Table, part_path: Path, dataset_path: str) -> None:
    """The table as published, as read back, with ``dataset_path`` in front
    (schema ``batch_combined``): the parts of every run have one schema. As
    read back: a list's items named ``element`` (the Parquet LIST
    convention) where Polars names them ``item``; only those columns are
    renamed, by a view of the same buffers (a cast would load
    pyarrow.compute, 0.16 s of CPU in every worker), the others taken as
    they are (a cast per column cost more than the encoding of a small part)."""
    # on workers only: the coordinating process never writes a table, nor loads polars (0.3 s of its imports)
    import pyarrow as pa

    from rotcal.tables import write_table

    fields, columns = [pa.field("dataset_path", pa.string())], [pa.array([dataset_path] * table.num_rows, pa.string())]
    for field, column in zip(table.schema, table.columns):
        if pa.types.is_large_list(field.type):
            field = field.with_type(pa.large_list(field.type.value_field.with_name("element")))
            column = pa.chunked_array([chunk.view(field.type) for chunk in column.chunks], field.type)
        fields.append(field)
        columns.append(column)
    metadata = {**(table.schema.metadata or {}), b"rotcal.combined": b"batch_combined 1.0"}
    write_table(pa.Table.from_arrays(columns, schema=pa.schema(fields, metadata=metadata)), part_path)


def detected_effects(diagnosis) -> tuple[str, ...]:
    """The effects a run's diagnosis detected, each once, in its order (none when not diagnosed)."""
    if diagnosis is None:
        return ()
    return tuple(dict.fromkeys(diagnosis.findings.filter(diagnosis.findings["detected"])["effect"].to_list()))


def run_job(job: Job) -> JobResult:
    """One dataset into ``job.work`` (``tables/`` and ``parts/``), on whatever
    worker runs it; the folder is removed unless the result is ok."""
    from rotcal.run import run_dataset  # the stages (scipy, the diagnosis) load on workers only

    started, clock = now(), time.perf_counter()
    work = Path(job.work)
    try:
        dataset_inputs(Path(job.source), job.config.limits)  # again: the worker reads the files now
        parts = work / "parts"
        outcome = run_dataset(Path(job.source), OutputDir(work / "tables", on_table=lambda name, table: _write_part(
            table, parts / f"{name}.parquet", job.dataset_path)), None, job.config, known=job.known)
        tables = [path for path in outcome.written if path.suffix == ".parquet"]  # not the report and its figures
        return JobResult("ok", None, tuple(p.stem for p in tables), started, time.perf_counter() - clock,
                         findings=detected_effects(outcome.diagnosis))
    except RotcalError as exc:  # one line, but for control characters in its path, escaped when printed
        status, reason = "quarantined", str(exc)
    except Exception as exc:  # a bug or the machine, not the data: retried on the next run
        status, reason = "error", " ".join(f"unexpected {type(exc).__name__} (a bug: please report it): {exc}".split())
    shutil.rmtree(work, ignore_errors=True)
    return JobResult(status, reason, (), started, time.perf_counter() - clock)


# -- executors --------------------------------------------------------------------

def _die_with_parent(parent_pid: int) -> None:
    """Pool worker start: end with the batch process (SIGKILL included), so
    no orphan goes on writing after it; leave Ctrl-C to the batch process."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if sys.platform.startswith("linux"):
        ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent_pid:
        os._exit(1)


# what every job loads, imported when a pool worker starts: the pool is
# opened at the first dataset to process and its workers import these
# (about a second of CPU each) while the batch process plans the others
JOB_MODULES = ("rotcal.run", "rotcal.diagnose", "rotcal.report.diagnosis", "rotcal.report.certificate", "pyarrow.parquet")


def _start_worker(parent_pid: int) -> None:
    """A pool worker's start: ``_die_with_parent``, then ``JOB_MODULES``. An
    import that fails is left to the job that needs it, which reports it as
    its dataset's error (a failed initializer would break the pool instead)."""
    _die_with_parent(parent_pid)
    for name in JOB_MODULES:
        with suppress(Exception):
            importlib.import_module(name)


def _started() -> None:
    """The task that starts a worker (its process starts at a submission)."""


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
        """A pool with its workers started now (one task each: a worker
        process starts at a submission), not at the first jobs."""
        pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_start_worker, initargs=(os.getpid(),))
        for _ in range(self.workers):
            pool.submit(_started)
        return pool

    def submit(self, fn, /, *args, **kwargs) -> Future:
        try:
            return self.pool.submit(fn, *args, **kwargs)
        except BrokenProcessPool:
            self.pool.shutdown(wait=False, cancel_futures=True)
            self.pool = self._new()
            return self.pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self.pool.shutdown(wait=wait, cancel_futures=cancel_futures)


# glibc's malloc in a pool worker: arrays of a dataset's size (0.4 MB a column
# of 54,000 samples) from the heap, and freed memory kept there for the next
# dataset, not handed back to the kernel to be faulted in again page by page.
# Measured (run_job in one process, 20 datasets, three alternations): mix
# 366 to 332 ms of CPU a dataset (page faults 359,000 to 149,000, system
# time halved), clean 230 to 223 ms. A whole batch of 100 on two workers:
# system time 5.4-7.4 to 3.1-3.4 s mix and 3.0 to 2.4 s clean, CPU from the
# same to 9 % less (user time rose a little: probably calloc zeroing reused
# heap memory itself). A worker keeps its peak heap; arrays past 64 MB
# (captures of millions of samples) are still mapped and unmapped, so a
# large run's peak memory does not grow. glibc reads these when a process
# starts: set for the spawned workers. Polars' jemalloc likewise keeps its
# freed pages a second, where rotcal's process default (rotcal/__init__.py)
# returns them at once for a large capture's peak memory: a dataset's Polars
# buffers are then reused by the next. Blocks past 8 MiB (jemalloc's
# oversize_threshold) are returned at once all the same, so a large capture's
# peak grows little. Measured (run_job in one process, 20 clean datasets,
# two alternations): page faults 5,100 to 1,100 a dataset, system time 21 to
# 13-14 ms of 178 (100 ms: 1,850 faults, 250 ms: 1,250); a batch of a
# 4.8-million-sample MCAP capture and a default-plan one: peak 650 to 705 MB.
WORKER_MALLOC = {"MALLOC_MMAP_THRESHOLD_": str(64 << 20), "MALLOC_TRIM_THRESHOLD_": str(256 << 20),
                 "_RJEM_MALLOC_CONF": "dirty_decay_ms:1000,muzzy_decay_ms:1000"}


@contextmanager
def _worker_environment(threads: int) -> Iterator[None]:
    """Pool workers started meanwhile size their Polars thread pools to
    their share of the cores (``POLARS_MAX_THREADS``, read when Polars is
    imported) and keep freed memory (``WORKER_MALLOC``), each unless the user set it:
    a pool per core in each worker made two workers' threads wake and wait
    on each other for every small frame (about a tenth of a dataset's CPU).
    Results do not depend on either."""
    wanted = {"POLARS_MAX_THREADS": str(threads), **WORKER_MALLOC}
    mine = {name for name in wanted if name not in os.environ}
    if rotcal.USER_JEMALLOC_CONF is None:  # it holds rotcal's process default (or Polars' own), not the user's
        mine.add("_RJEM_MALLOC_CONF")
    before = {name: os.environ.get(name) for name in mine}
    os.environ.update({name: wanted[name] for name in mine})
    try:
        yield
    finally:
        for name, value in before.items():
            if value is None:
                del os.environ[name]
            else:
                os.environ[name] = value


@contextmanager
def open_executor(batch: BatchConfig, jobs: int) -> Iterator[tuple[Executor, int]]:
    """The executor of ``batch.executor`` and how many jobs it runs at once."""
    match = EXECUTOR.fullmatch(batch.executor)
    if match is None:  # a BatchConfig's executor is valid by construction
        raise ConfigError(f"executor {batch.executor!r} is not 'local' or 'dask://HOST:PORT'")
    if match.group(1) is None:
        workers = min(cores(batch.workers), jobs)
        if workers == 1:
            with _InProcess() as executor:
                yield executor, workers
            return
        with _worker_environment(share(batch.workers, workers)), _LocalPool(workers) as executor:
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


def execute(executor: Executor, workers: int, jobs: list[tuple[Plan, Job]]) -> Iterator[tuple[Plan, JobResult]]:
    """Results as jobs finish, with at most two per worker submitted at a time."""
    queue, running = deque(jobs), dict[Future, Plan]()
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
                result = JobResult("error", " ".join(f"the worker failed: {type(exc).__name__}: {exc}".split()), (), now(), 0.0)
            yield plan, result

