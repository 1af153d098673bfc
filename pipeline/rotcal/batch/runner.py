"""``rotcal batch``: every new or changed dataset under ROOT through
``run.run_dataset``, on a local process pool or a Dask cluster, with results
published atomically into DIR (``manifest.Layout``) and a manifest saying
what was done (``manifest.Manifest``). Batch holds no pipeline logic.

A run finds and identifies the datasets (``plan``), runs the new or changed
ones (``jobs``) and publishes what they produced (here). A dataset is
re-processed when the SHA-256 of any input, the configuration or the rotcal
version changes (its fingerprint); docs/batch.md has the rules.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import Executor
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime
from pathlib import Path

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, SpinnerColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn

from rotcal import __version__
from rotcal.batch.jobs import Job, JobResult, execute, open_executor
from rotcal.batch.manifest import DatasetRecord, Layout, Manifest, now, run_lock
from rotcal.batch.plan import Plan, batch_site, config_json, discover, plan_dataset, shared_certificate_numbers
from rotcal.config import RunConfig, RunSection
from rotcal.errors import ExitCode, InputError, printable
from rotcal.parallel import share

# -- progress -----------------------------------------------------------------------

class Reporter:
    """A batch run's progress on ``console``: a rich progress bar with a line
    per dataset on a terminal, plain time-stamped log lines otherwise; nothing
    without a console."""

    def __init__(self, console: Console | None = None):
        self.console, self.done, self.total = console, 0, 0
        self.progress: Progress | None = None

    def __enter__(self) -> Reporter:
        return self

    def __exit__(self, *exc) -> None:
        if self.progress is not None:
            self.progress.stop()

    def _print(self, text: str, style: str = "") -> None:
        if self.progress is not None:
            self.progress.console.print(text, style=style, highlight=False, markup=False, soft_wrap=True)
        elif self.console is not None:
            self.console.print(f"{now()} rotcal batch: {text}", highlight=False, markup=False, soft_wrap=True)

    def note(self, text: str) -> None:
        self._print(text)

    def start(self, discovered: int, unchanged: int, total: int) -> None:
        self.total = total
        self.note(f"{discovered} datasets found: {unchanged} unchanged, {total} to process")
        if self.console is not None and self.console.is_terminal and total:
            # markup off: the description holds a dataset's name, which may hold [brackets]
            self.progress = Progress(SpinnerColumn(), TextColumn("{task.description}", markup=False), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), TimeRemainingColumn(), console=self.console)
            self.progress.start()
            self.task = self.progress.add_task("rotcal batch", total=total)

    def dataset(self, dataset_path: str, result: JobResult) -> None:
        self.done += 1
        dataset_path = printable(dataset_path)
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
    findings: tuple[dict, ...] = ()  # this run's datasets whose diagnosis found something: dataset_path, effects

    @property
    def exit_status(self) -> ExitCode:
        """OK all published; QUARANTINED a dataset is in quarantine (new or
        unchanged); FAILED a dataset failed unexpectedly (retried next run)."""
        if self.errors:
            return ExitCode.FAILED
        return ExitCode.QUARANTINED if self.quarantined or self.still_quarantined else ExitCode.OK

    def as_dict(self) -> dict:
        return {**asdict(self), "problems": list(self.problems), "notes": list(self.notes), "findings": list(self.findings),
                "exit_status": int(self.exit_status)}

    def text(self) -> str:
        lines = [f"{self.discovered} datasets: {self.processed} processed ({self.ok} ok, {self.quarantined} quarantined, "
                 f"{self.errors} errors), {self.unchanged} unchanged ({self.still_quarantined} still quarantined); "
                 f"{self.wall_s:.1f} s"]
        lines += [f"{p['status']}: {printable(p['dataset_path'])}: {p['reason']}" for p in self.problems]
        if self.findings:  # the datasets to look at: their report.md says what was found and modelled
            lines.append(f"{len(self.findings)} dataset{'s' if len(self.findings) > 1 else ''} with findings (see each one's report.md):")
            lines += [f"finding: {printable(f['dataset_path'])}: {', '.join(f['effects'])}" for f in self.findings]
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
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a file, or not writable (the CLI checks first: this is for library callers)
        raise InputError(f"the output directory cannot be made: {exc.strerror}", path=out) from None
    return root, out


def run_batch(root: Path, out: Path, config: RunConfig = RunConfig(), reporter: Reporter | None = None) -> BatchSummary:
    """Process every new or changed dataset under ``root`` into ``out``.

    Raises ``InputError`` for a bad ROOT or site file, ``ConfigError`` for a Dask scheduler it cannot reach,
    ``manifest.LockedError`` when another run holds ``out``'s lock. Bad
    datasets do not raise: they are quarantined with their reason.
    """
    root, out = _checked_dirs(root, out)
    config = batch_site(root, config)
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


def _plan(root: Path, out: Path, config: RunConfig, config_text: str, manifest: Manifest, layout: Layout,
          previous: dict[str, DatasetRecord], start: Callable[[int], None]) -> tuple[list[Plan], ...]:
    """Every dataset under ``root`` planned (``plan_dataset``), as (all,
    to process, refused, unchanged); ``start(n)`` called at the first one to
    process, with at most ``n`` to come, so that the executor's workers start
    (their imports) while the others are planned."""
    plans: list[Plan] = []
    todo: list[Plan] = []
    refused: list[Plan] = []
    unchanged: list[Plan] = []
    with manifest.transaction():
        found = discover(root, out)
        for k, dataset in enumerate(found):
            plan = plan_dataset(dataset, root, config, manifest, config_text)
            prev = previous.get(plan.found.dataset_path)
            current = prev is not None and prev.fingerprint == plan.fingerprint and (
                prev.status == "quarantined" or (prev.status == "ok" and layout.published(plan.dataset_id) == prev.output))
            (unchanged if current else refused if plan.refusal else todo).append(plan)
            plans.append(plan)
            if todo == [plan]:
                start(len(found) - k)
    return plans, todo, refused, unchanged


def _run(root: Path, out: Path, config: RunConfig, manifest: Manifest, reporter: Reporter, clock: float,
         notes: tuple[str, ...]) -> BatchSummary:
    layout = Layout(out)
    layout.sweep()
    run_id = f"{datetime.now(UTC):%Y%m%dT%H%M%S.%fZ}-{os.getpid()}"
    previous = manifest.records()
    config_text = config_json(config)  # the configuration results depend on, once a run
    with ExitStack() as stack:
        opened: list[tuple[Executor, int]] = []
        plans, todo, refused, unchanged = _plan(root, out, config, config_text, manifest, layout, previous, lambda most: opened.append(
            stack.enter_context(open_executor(config.batch, most))))
        local, workers = config.batch.executor == "local", 0
        for note in shared_certificate_numbers(plans):
            notes += (note,)
            reporter.note(note)
        dead = manifest.start_run(run_id, now(), str(root), config.batch.executor, config.batch.workers, __version__)
        if dead:
            were = "runs were" if len(dead) > 1 else "run was"
            notes += (f"{len(dead)} earlier {were} interrupted ({', '.join(dead[:5])}{', ...' if len(dead) > 5 else ''})",)
            reporter.note(notes[-1])
        reporter.start(len(plans), len(unchanged), len(todo) + len(refused))
        outcomes: list[tuple[Plan, JobResult]] = []

        def settle(plan: Plan, result: JobResult, work: Path | None) -> None:
            if result.status == "ok" and result.rotcal_version != __version__:
                result = replace(result, status="error", reason=f"the worker runs rotcal {result.rotcal_version}, this run {__version__}")
            output = None
            if result.status == "ok" and work is not None:  # a refused plan settles with no work folder
                output = layout.publish(plan.dataset_id, plan.fingerprint, work)
            else:
                layout.withdraw(plan.dataset_id)
                if work is not None:
                    shutil.rmtree(work, ignore_errors=True)
            if result.reason is not None:
                result = replace(result, reason=printable(result.reason))
            manifest.put(DatasetRecord(
                plan.found.dataset_path, plan.dataset_id, result.status, plan.fingerprint, plan.inputs, config_text,
                __version__, result.reason, output, json.dumps(result.tables), run_id, result.started_at, now(), result.duration_s))
            outcomes.append((plan, result))
            reporter.dataset(plan.found.dataset_path, result)

        for plan in refused:
            settle(plan, JobResult("quarantined", plan.refusal, (), now(), 0.0), None)
        if todo:
            executor, workers = opened[0]
            # each run's threads get its share of the batch's cores; results do not depend on it
            job_config = replace(config, run=RunSection(workers=share(config.batch.workers, workers) if local else 1))
            jobs = [(plan, Job(plan.found.dataset_path, str(plan.found.source),
                               str(layout.work / f"{plan.dataset_id}.{run_id}"), job_config, plan.known)) for plan in todo]
            for plan, result in execute(executor, workers, jobs):
                settle(plan, result, layout.work / f"{plan.dataset_id}.{run_id}")
    records = manifest.records()
    combined = layout.publish_combined({r.dataset_id: r.output for r in records.values()
                                        if r.status == "ok" and r.output is not None
                                        and layout.published(r.dataset_id) == r.output})
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
        findings=tuple({"dataset_path": p.found.dataset_path, "effects": list(r.findings)} for p, r in outcomes if r.findings),
    )
    manifest.finish_run(run_id, now(), json.dumps(summary.as_dict()))
    return summary

