"""``rotcal batch``, first step: the datasets under ROOT and the identity of
each this run (its input files' SHA-256, the configuration the results
depend on, the rotcal version), or why it is refused, before anything runs.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
from dataclasses import asdict, dataclass, replace
from pathlib import Path

from rotcal import __version__
from rotcal.batch.manifest import Manifest
from rotcal.config import Limits, RunConfig
from rotcal.errors import InputError, LimitError, RotcalError, decoded
from rotcal.ingest.files import capture_files
from rotcal.ingest.formats import is_capture
from rotcal.ingest.meta import load_meta
from rotcal.ingest.site import SITE_FILE, load_site

_CLEAN_PART = re.compile(r"[A-Za-z0-9.-]+(?:_[A-Za-z0-9.-]+)*")


# -- what the datasets are ----------------------------------------------------

@dataclass(frozen=True)
class Found:
    """A dataset under ROOT: its path relative to ROOT (bytes that are not
    UTF-8 shown as ``\\xNN``) and where it is."""

    dataset_path: str
    source: Path


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
    ``dataset_inputs`` refuses), nor is a subdirectory that cannot be listed
    (reported as a dataset, which the planner refuses with the reason).
    """
    found, stack = [], [root]
    while stack:
        directory = stack.pop()
        try:
            with os.scandir(directory) as it:
                entries = [e for e in it if not e.name.startswith(".")]
        except OSError as exc:
            if directory == root:
                raise InputError(f"ROOT cannot be listed: {exc.strerror}", path=root) from None
            found.append(Found(decoded(directory.relative_to(root).as_posix()), directory))
            continue
        for entry in entries:
            path = Path(entry.path)
            rel = decoded(path.relative_to(root).as_posix())
            if entry.is_dir(follow_symlinks=False):
                if path == out:
                    continue
                if (path / "dataset.toml").is_file() or (path / "dataset.toml").is_symlink():
                    found.append(Found(rel, path))
                else:
                    stack.append(path)
            elif entry.is_symlink() and path.is_dir():
                found.append(Found(rel, path))
            elif is_capture(path):
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
    # capture_files refuses, with the same line, a capture that resolves outside the directory
    return [toml] + [file for file, _ in capture_files(source, load_meta(toml))]


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


def batch_site(root: Path, config: RunConfig) -> RunConfig:
    """``config`` with the batch's site file: ``[report] site`` (``--site``),
    else ROOT's ``site.toml`` when there is one, for every dataset; checked
    once here (a bad one is the whole batch's error, ``InputError``)."""
    given = config.report.site or (str(root / SITE_FILE) if (root / SITE_FILE).is_file() else "")
    if not given:
        return config
    site = load_site(Path(given))
    assert site.site_file is not None
    return replace(config, report=replace(config.report, site=site.site_file.path))


def shared_certificate_numbers(plans: list[Plan]) -> tuple[str, ...]:
    """A note per certificate number that more than one dataset's
    ``dataset.toml`` gives (a certificate number identifies one certificate,
    ISO/IEC 17025:2017 7.8.2.1 e); the refused datasets left out."""
    holders: dict[str, list[str]] = {}
    for plan in plans:
        toml = plan.found.source / "dataset.toml"
        if plan.refusal is None and toml.is_file():
            number = load_meta(toml).identification.certificate.number
            if number is not None:
                holders.setdefault(number, []).append(plan.found.dataset_path)
    return tuple(f"certificate number {number!r} is given by {len(paths)} datasets ({', '.join(paths)}): "
                 "each certificate needs its own" for number, paths in sorted(holders.items()) if len(paths) > 1)


def config_json(config: RunConfig) -> str:
    """The configuration results depend on: every table but the cores and
    executors (``[run]``, ``[batch]``); the site file by its content, so that
    a changed site file (the certificates' laboratory fields) reruns the datasets."""
    doc = asdict(config)
    for key in ("run", "batch"):
        doc.pop(key)
    site = doc["report"]["site"]
    if site:
        doc["report"]["site"] = hashlib.sha256(Path(site).read_bytes()).hexdigest()
    return json.dumps(doc, sort_keys=True)


@dataclass(frozen=True)
class Plan:
    """A dataset's identity this run: inputs and fingerprint, or why it is
    refused; ``known``: the inputs' SHA-256s by ``file_identity`` (those
    it vouches for), so that the job does not read them again to hash them."""

    found: Found
    dataset_id: str
    fingerprint: str
    inputs: str
    refusal: str | None
    known: dict[tuple[int, ...], str]


def _refusal(exc: Exception, found: Found) -> str:
    """Why a dataset is refused, in one line."""
    if isinstance(exc, RotcalError):
        return str(exc)
    if isinstance(exc, OSError):  # unreadable, or gone since it was found
        return str(InputError(f"cannot be read: {exc.strerror or exc}", path=decoded(str(exc.filename or found.source))))
    # Anything else is a bug met by this dataset's inputs: the dataset is
    # quarantined (retried when it changes) and the others go on.
    return str(InputError(f"unexpected {type(exc).__name__} while planning (a bug: please report it): {exc}",
                          path=decoded(str(found.source))))


def plan_dataset(found: Found, root: Path, config: RunConfig, manifest: Manifest, config_text: str) -> Plan:
    """Hash the dataset's inputs (``manifest.digest``), or say why it is
    refused; ``config_text`` is ``config_json(config)``, made once a run."""
    try:
        if found.dataset_path != found.source.relative_to(root).as_posix():
            raise InputError("the path is not valid UTF-8 (rename it)", path=found.dataset_path)
        files = dataset_inputs(found.source, config.limits)
        digests = [(f, *manifest.digest(f)) for f in files]
        inputs: list[list[object]] = [[decoded(f.relative_to(root).as_posix()), sha] for f, sha, _ in digests]
        known = {identity: sha for _, sha, identity in digests if identity is not None}
        refusal = None
    except Exception as exc:  # the one guard around a dataset's planning: nothing in it stops the others
        refusal, known = _refusal(exc, found), {}
        try:
            inputs = [["listing", _listing(found.source)]]
        except OSError:
            inputs = [["listing", None]]
    identity = {"dataset": found.dataset_path, "inputs": inputs, "config": config_text, "rotcal": __version__}
    fingerprint = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()
    return Plan(found, dataset_id(found.dataset_path), fingerprint, json.dumps(inputs), refusal, known)

