"""Mutation fuzzer over every input form rotcal reads (docs/fuzzing.md).

    python scripts/fuzz.py --inputs 100000 --seed 1 --workers 2 --failures fuzz-failures

Input ``i`` of seed ``S`` is drawn from ``numpy.random.default_rng([S, i])``:
its form (round robin over ``FORMS``), its mutation and the mutation's
choices, so a run is the same for a seed whatever the worker count, and
``--only i`` replays one input. The invariant, for every input:

- a ``RotcalError`` of exit status 2 (``InputError``, ``ConfigError``) whose
  message is one printable line naming a file; or
- a result whose every float (samples, segments, fits, time base; every
  table a full ``run_dataset`` publishes, for one input in ``--full-every``)
  is finite, and which equals the seed's result when the mutation is neutral;
- never any other exception, never longer than ``--budget-s`` seconds (a
  watchdog thread interrupts the input, and ends the worker if the input
  does not return), never a worker whose RSS high-water mark
  (``getrusage``) passes ``--memory-mib``.

Every input that breaks it is saved under ``--failures`` (the mutated files
and what went wrong); the exit status is 1 if any did.
"""

from __future__ import annotations

import argparse
import hashlib
import multiprocessing as mp
import os
import queue
import resource
import shutil
import signal
import sys
import tempfile
import threading
import time
import traceback
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import fuzz_inputs as fi  # noqa: E402
from fuzz_seeds import FORMS, Form, build_seeds  # noqa: E402

HOSTILE_NAMES = ("[1]", "*", "?", "\n", "\x1b[31m", ":x:", " ", "\\", "'")


@dataclass(frozen=True)
class Verdict:
    """One input's outcome: ``refused`` (exit 2), ``result``, ``undetermined``
    (exit 3 after a full run), or a failure kind with its detail."""

    index: int
    form: str
    mutation: str
    outcome: str
    detail: str = ""
    full: bool = False

    @property
    def failed(self) -> bool:
        return self.outcome not in ("refused", "result", "undetermined")


def draw(index: int, seed: int, full_every: int) -> tuple[Form, fi.Mutation | str, bool, object]:
    import numpy as np

    rng = np.random.default_rng([seed, index])
    form = FORMS[index % len(FORMS)]
    choices = [*form.mutations, *(["hostile_name"] if form.renamable else [])]
    return form, fi.pick(rng, choices), bool(full_every) and rng.random() < 1 / full_every, rng


def mutate(form: Form, mutation: fi.Mutation | str, seeds: Path, work: Path, rng) -> tuple[Path, dict]:
    """The mutated input's directory (a copy of the seed's) and what was renamed."""
    if work.exists():
        shutil.rmtree(work)
    work = work / form.name  # the dataset's name is its directory's: the same as the seed's
    shutil.copytree(seeds / form.name, work)
    target = work / fi.pick(rng, sorted(p.name for p in work.glob(form.target)))
    if mutation == "hostile_name":
        name = f"{target.stem}{fi.pick(rng, HOSTILE_NAMES)}{target.suffix}"
        target.rename(work / name)
        return work, {name: target.name}
    target.write_bytes(mutation.apply(target.read_bytes(), rng))
    return work, {}


def fingerprint(directory: Path, *context: object) -> str:
    """The mutated input's files (names and bytes) and what its verdict depends on besides."""
    digest = hashlib.sha256(repr(context).encode())
    for path in sorted(directory.iterdir()):
        digest.update(os.fsencode(path.name) + b"\0" + path.read_bytes())
    return digest.hexdigest()


def check(index: int, seed: int, seeds: Path, work: Path, failures: Path | None, reference: dict, full_every: int,
          seen: dict | None = None) -> Verdict:
    """One input's verdict; ``seen`` keeps the verdicts of inputs already
    checked by their fingerprint (many mutations give the same bytes: a
    dropped summary, CRLF line ends), so that each distinct input runs once."""
    from rotcal.errors import ExitCode, RotcalError, UndeterminedError

    form, mutation, full, rng = draw(index, seed, full_every)
    name = mutation if isinstance(mutation, str) else mutation.name
    neutral = name == "hostile_name" or (not isinstance(mutation, str) and mutation.neutral)
    verdict = Verdict(index, form.name, name, "result", full=full)
    directory = work
    key = ""
    try:
        directory, renamed = mutate(form, mutation, seeds, work, rng)
        key = fingerprint(directory, form.name, full, neutral, sorted(renamed.items()))
        if seen is not None and key in seen:
            outcome, detail = seen[key]
            verdict = Verdict(index, form.name, name, outcome, detail, full)
            if verdict.failed and failures is not None:
                save(verdict, directory, failures, seed)
            return verdict
        result = form.run(directory, seeds, full, work.parent / "out")
        if result.nonfinite:
            verdict = Verdict(index, form.name, name, "nonfinite", result.nonfinite, full)
        elif neutral and form.name in reference and not form.same(reference[form.name], result, renamed):
            verdict = Verdict(index, form.name, name, "mismatch", "a neutral mutation changed the result", full)
        elif result.undetermined:
            verdict = Verdict(index, form.name, name, "undetermined", full=full)
    except RotcalError as exc:
        from rotcal.errors import printable

        text = printable(str(exc))
        if isinstance(exc, UndeterminedError):
            verdict = Verdict(index, form.name, name, "undetermined", full=full)
        elif exc.exit_code != ExitCode.BAD_INPUT:
            verdict = Verdict(index, form.name, name, "exception", f"exit {exc.exit_code}: {text}", full)
        elif "\n" in text or exc.path is None:
            verdict = Verdict(index, form.name, name, "message", f"not one line naming a file: {text!r}", full)
        else:
            verdict = Verdict(index, form.name, name, "refused", full=full)
    except KeyboardInterrupt:  # the watchdog's interrupt
        verdict = Verdict(index, form.name, name, "hang", "over the time budget", full)
    except BaseException:
        verdict = Verdict(index, form.name, name, "exception", traceback.format_exc(), full)
    if verdict.failed and failures is not None:
        save(verdict, directory, failures, seed)
    if seen is not None and key and verdict.outcome != "hang":
        seen[key] = (verdict.outcome, verdict.detail)
    return verdict


def save(verdict: Verdict, directory: Path, failures: Path, seed: int) -> None:
    """The reproducer: the mutated input and what went wrong."""
    where = failures / f"{verdict.form}-{verdict.mutation}-{verdict.index}"
    if where.exists():
        shutil.rmtree(where)
    if directory.exists():
        shutil.copytree(directory, where / "input", symlinks=True)
    where.mkdir(parents=True, exist_ok=True)
    (where / "FAILURE.txt").write_text(
        f"{verdict.outcome}: form {verdict.form}, mutation {verdict.mutation}, full run {verdict.full}\n"
        f"replay: python scripts/fuzz.py --seed {seed} --only {verdict.index}\n\n{verdict.detail}\n")


class Watchdog(threading.Thread):
    """Interrupts the main thread when an input runs past ``budget`` seconds
    (``KeyboardInterrupt`` at its next Python bytecode) and ends the process
    (exit 70) when it has not returned ``budget`` seconds later: the parent
    then counts the input as a hang and starts another worker."""

    def __init__(self, budget: float, on_kill):
        super().__init__(daemon=True)
        self.budget, self.on_kill, self.started_at, self.interrupted = budget, on_kill, None, False

    def run(self) -> None:
        import _thread

        while True:
            time.sleep(min(1.0, self.budget / 4))
            started = self.started_at
            if started is None:
                continue
            late = time.monotonic() - started
            if late > 2 * self.budget:
                self.on_kill()
                os._exit(70)
            if late > self.budget and not self.interrupted:
                self.interrupted = True
                _thread.interrupt_main()

    def begin(self) -> None:
        self.interrupted, self.started_at = False, time.monotonic()

    def end(self) -> None:
        self.started_at = None


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def worker(indices: list[int], seed: int, failures: Path | None, budget: float, memory_mib: float, full_every: int,
           results: mp.Queue) -> None:
    scratch = Path(tempfile.mkdtemp(prefix="rotcal-fuzz-", dir="/dev/shm" if os.path.isdir("/dev/shm") else None))
    try:
        try:
            seeds = build_seeds(scratch / "seeds")
            reference = {f.name: f.run(seeds / f.name, seeds, False, scratch / "out") for f in FORMS}
        except Exception:  # the seeds themselves fail: nothing to fuzz
            results.put(("setup", traceback.format_exc(), 0.0))
            return
        current: list[int] = []

        def killed() -> None:
            form, mutation, full, _ = draw(current[0], seed, full_every)
            name = mutation if isinstance(mutation, str) else mutation.name
            verdict = Verdict(current[0], form.name, name, "hang", "did not return: worker ended", full)
            if failures is not None:
                save(verdict, scratch / "work", failures, seed)
            results.put(("killed", verdict, peak_mib()))
            results.close()
            results.join_thread()  # the verdict out before the process ends

        seen: dict[str, tuple[str, str]] = {}
        watchdog = Watchdog(budget, killed)
        watchdog.start()
        over = False
        for index in indices:
            current[:] = [index]
            watchdog.begin()
            verdict = check(index, seed, seeds, scratch / "work", failures, reference, full_every, seen)
            watchdog.end()
            peak = peak_mib()
            if peak > memory_mib and not over and not verdict.failed:
                over = True
                verdict = Verdict(index, verdict.form, verdict.mutation, "memory", f"RSS high-water {peak:.0f} MiB", verdict.full)
            results.put(("verdict", verdict, peak))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


def run(inputs: int, seed: int, workers: int, failures: Path | None, budget: float, memory_mib: float, full_every: int,
        only: int | None = None, progress: int = 0) -> tuple[list[Verdict], float]:
    """Every verdict (ordered by input) and the largest RSS high-water mark of a worker, MiB."""
    began = time.monotonic()
    todo = [only] if only is not None else list(range(inputs))
    context = mp.get_context("spawn")
    results: mp.Queue = context.Queue()
    pending = {w: todo[w::workers] for w in range(workers)}
    procs = {}

    def start(w: int) -> None:
        procs[w] = context.Process(target=worker, args=(pending[w], seed, failures, budget, memory_mib, full_every, results))
        procs[w].start()

    for w in range(workers):
        if pending[w]:
            start(w)
    verdicts: dict[int, Verdict] = {}
    peaks: list[float] = []
    owner = {i: w for w, items in pending.items() for i in items}
    def stop(*_: object) -> None:
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, stop)  # a run stopped early still reports the inputs it checked
    try:
        collect(todo, verdicts, results, procs, pending, owner, start, progress, began, peaks)
    except KeyboardInterrupt:
        for proc in procs.values():
            proc.terminate()
        print(f"interrupted after {len(verdicts)} of {len(todo)} inputs", file=sys.stderr, flush=True)
    for proc in procs.values():
        proc.join()
    return [verdicts[i] for i in sorted(verdicts)], max(peaks, default=0.0)


def collect(todo, verdicts, results, procs, pending, owner, start, progress, began, peaks) -> None:
    """Gather the workers' verdicts; a worker that ends without one (a crash)
    or is ended by its watchdog (a hang) is replaced by one that goes on after the input."""
    while len(verdicts) < len(todo):
        try:
            kind, verdict, worker_peak = results.get(timeout=5)
        except queue.Empty:
            for w, proc in list(procs.items()):
                if not proc.is_alive() and pending[w]:  # ended without its last verdict (a crash): count it, go on after it
                    lost = pending[w].pop(0)
                    verdicts[lost] = Verdict(lost, FORMS[lost % len(FORMS)].name, "?", "crash", f"worker exit {proc.exitcode}")
                    if pending[w]:
                        start(w)
            continue
        if kind == "setup":
            for proc in procs.values():
                proc.kill()
            raise SystemExit(f"the seeds cannot be built or read:\n{verdict}")
        verdicts[verdict.index] = verdict
        peaks.append(worker_peak)
        if progress and len(verdicts) % progress == 0:
            failed = sum(v.failed for v in verdicts.values())
            print(f"{len(verdicts)} inputs, {failed} failures, {time.monotonic() - began:.0f} s", file=sys.stderr, flush=True)
        w = owner[verdict.index]
        if verdict.index in pending[w]:
            pending[w].remove(verdict.index)
        if kind == "killed":  # the watchdog ended the worker: the next one goes on after the input
            procs[w].join()
            if pending[w]:
                start(w)


def report(verdicts: list[Verdict], peak: float, seconds: float, memory_mib: float) -> str:
    by_form: dict[str, Counter] = {}
    by_mutation: dict[str, Counter] = {}
    for v in verdicts:
        for table, key in ((by_form, v.form), (by_mutation, v.mutation)):
            counts = table.setdefault(key, Counter())
            counts["inputs"] += 1
            counts["failed" if v.failed else v.outcome] += 1
            counts["full runs"] += v.full
    columns = ("inputs", "refused", "result", "undetermined", "full runs", "failed")
    lines = []
    for title, table in (("form", by_form), ("mutation", by_mutation)):
        lines.append(f"{title:<24}" + "".join(f"{c:>13}" for c in columns))
        for key in sorted(table):
            lines.append(f"{key:<24}" + "".join(f"{table[key][c]:>13}" for c in columns))
        lines.append("")
    failed = [v for v in verdicts if v.failed]
    kinds = Counter(v.outcome for v in failed)
    lines.append(f"{len(verdicts)} inputs in {seconds:.0f} s ({len(verdicts) / max(seconds, 1e-9):.1f} inputs/s); "
                 f"failures: {len(failed)} {dict(kinds) if kinds else ''}; worker RSS high-water {peak:.0f} MiB "
                 f"(bound {memory_mib:.0f} MiB)")
    for v in failed[:20]:
        lines.append(f"  input {v.index} ({v.form}, {v.mutation}): {v.outcome}: {v.detail.strip().splitlines()[-1] if v.detail else ''}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--inputs", type=int, default=1000, help="mutated inputs to try")
    parser.add_argument("--seed", type=int, default=1, help="the run's seed: the same seed gives the same inputs")
    parser.add_argument("--workers", type=int, default=2, help="worker processes")
    parser.add_argument("--failures", type=Path, default=Path("fuzz-failures"), help="where reproducers are saved")
    parser.add_argument("--budget-s", type=float, default=30.0, help="time budget of one input, seconds")
    parser.add_argument("--memory-mib", type=float, default=1024.0, help="bound on a worker's RSS high-water mark, MiB")
    parser.add_argument("--full-every", type=int, default=40, help="a full run_dataset for one input in this many (0: none)")
    parser.add_argument("--progress", type=int, default=0, help="print a line to stderr every this many inputs")
    parser.add_argument("--only", type=int, default=None, help="replay the one input of this index")
    args = parser.parse_args(argv)
    began = time.monotonic()
    verdicts, peak = run(args.inputs, args.seed, max(1, args.workers), args.failures, args.budget_s, args.memory_mib,
                         args.full_every, args.only, args.progress)
    print(report(verdicts, peak, time.monotonic() - began, args.memory_mib))
    return 1 if any(v.failed for v in verdicts) or peak > args.memory_mib else 0


if __name__ == "__main__":
    sys.exit(main())
