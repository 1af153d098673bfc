"""The batch's per-dataset savings keep what they save on: a part written
from the published Arrow table is the part read back from the published
file, byte for byte; the pool's workers size Polars to their core share;
the reductions' shared rate segments are those of the table asked for."""

from __future__ import annotations

import os

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

import rotcal
from rotcal.batch.jobs import WORKER_MALLOC, _write_part, open_executor
from rotcal.combine.labelled import rate_segments, segment_coefficients
from rotcal.config import BatchConfig
from rotcal.tables import PARQUET_OPTIONS, write_table


def test_a_part_is_the_published_file_read_back_with_its_dataset_path(tmp_path):
    table = pl.DataFrame({"segment": [1, 2], "cov_u": [[1.0, 2.0], [3.0, float("nan")]]}).to_arrow()
    table = table.replace_schema_metadata({b"rotcal.schema": b"fits"})
    published = write_table(table, tmp_path / "fits.parquet")
    # the part as the batch wrote it before: the file read back, the path column in front
    read = pq.ParquetFile(published).read()
    read = read.add_column(0, pa.field("dataset_path", pa.string()), pa.array(["lot/dut1"] * 2, pa.string()))
    pq.write_table(read.replace_schema_metadata({**read.schema.metadata, b"rotcal.combined": b"batch_combined 1.0"}),
                   tmp_path / "expected.parquet", **PARQUET_OPTIONS)
    _write_part(table, tmp_path / "parts" / "fits.parquet", "lot/dut1")
    assert (tmp_path / "parts" / "fits.parquet").read_bytes() == (tmp_path / "expected.parquet").read_bytes()


def _worker_settings(_: int) -> tuple[int, str | None, str | None, str]:
    import polars

    return (polars.thread_pool_size(), os.environ.get("MALLOC_MMAP_THRESHOLD_"), os.environ.get("MALLOC_TRIM_THRESHOLD_"),
            os.environ["_RJEM_MALLOC_CONF"])


def test_pool_workers_size_polars_to_their_share_of_the_cores_and_keep_freed_memory(monkeypatch):
    monkeypatch.setattr(rotcal, "USER_JEMALLOC_CONF", None)  # as in a shell without the variable
    conf = os.environ["_RJEM_MALLOC_CONF"]  # rotcal's process default, as Polars left it here
    assert "POLARS_MAX_THREADS" not in os.environ and "MALLOC_MMAP_THRESHOLD_" not in os.environ
    with open_executor(BatchConfig(workers=2), 4) as (executor, workers):
        settings = [f.result() for f in [executor.submit(_worker_settings, k) for k in range(4)]]
    # two cores, two workers: one thread each; malloc keeps 64 MB arrays on the heap, 256 MB freed;
    # Polars' jemalloc keeps freed pages a second (Polars puts its own defaults before the setting)
    assert workers == 2 and [s[:3] for s in settings] == [(1, str(64 << 20), str(256 << 20))] * 4
    assert all(s[3].endswith(",dirty_decay_ms:1000,muzzy_decay_ms:1000") for s in settings), settings
    assert WORKER_MALLOC == {"MALLOC_MMAP_THRESHOLD_": "67108864", "MALLOC_TRIM_THRESHOLD_": "268435456",
                             "_RJEM_MALLOC_CONF": "dirty_decay_ms:1000,muzzy_decay_ms:1000"}
    # the batch process's environment as it was
    assert not {"POLARS_MAX_THREADS", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"} & set(os.environ)
    assert os.environ["_RJEM_MALLOC_CONF"] == conf


def test_a_users_own_allocator_settings_reach_the_workers(monkeypatch):
    monkeypatch.setenv("_RJEM_MALLOC_CONF", "dirty_decay_ms:7")
    monkeypatch.setattr(rotcal, "USER_JEMALLOC_CONF", "dirty_decay_ms:7")  # as importing rotcal found it
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "12345")
    with open_executor(BatchConfig(workers=2), 2) as (executor, _):
        settings = [f.result() for f in [executor.submit(_worker_settings, k) for k in range(2)]]
    assert all(s[2] == "12345" and s[3].endswith(",dirty_decay_ms:7") for s in settings), settings
    assert os.environ["_RJEM_MALLOC_CONF"] == "dirty_decay_ms:7" and os.environ["MALLOC_TRIM_THRESHOLD_"] == "12345"


def _fits(segments: list[tuple[int, str, float, str]], scale: float) -> pl.DataFrame:
    """A fits table: per segment (number, axis, rate, kind) three channels' C, A, B and covariances."""
    rows = []
    for seg, axis, rate, kind in segments:
        for k, channel in enumerate("uvw"):
            c, a, b = scale * (seg + k), scale * (seg - k), scale * k
            rows.append({"segment": seg, "axis": axis, "rate_hz": rate, "kind": kind, "channel": channel, "status": "ok",
                         "dof": 100, "C": c, "A": a, "B": b,
                         **{f"cov_{o}": list(np.eye(3).ravel() * (k == j) * scale) for j, o in enumerate("uvw")}})
    return pl.DataFrame(rows)


def test_rate_segments_are_those_of_the_table_asked_for():
    first = _fits([(0, "x", 0.0, "static"), (1, "x", 0.5, "rotation")], 1.0)
    second = _fits([(0, "y", 0.0, "static"), (1, "y", 0.5, "rotation"), (2, "z", 1.0, "rotation")], 2.0)
    for fits, rates in ((first, [0.0, 0.5]), (second, [0.0, 0.5, 1.0]), (first, [0.0, 0.5])):
        got = rate_segments(fits)
        assert [rate for rate, _ in got] == rates
        expected = segment_coefficients(fits)
        flat = [s for _, segs in got for s in segs]
        assert [(s.segment, s.axis) for s in flat] == [(s.segment, s.axis) for s in expected]
        assert all(np.array_equal(s.coef, e.coef) and np.array_equal(s.cov, e.cov) for s, e in zip(flat, expected))
    again = rate_segments(first)  # the same table asked for again: the same answer, in a list of its own
    assert again is not rate_segments(first) and [r for r, _ in again] == [0.0, 0.5]


def test_a_job_takes_the_hashes_its_dataset_was_planned_with_unless_a_file_changed(tmp_path, monkeypatch):
    import hashlib
    import json

    from rotcal.batch.manifest import Manifest
    from rotcal.batch.plan import config_json, discover, plan_dataset
    from rotcal.batch.runner import run_batch
    from rotcal.ingest.duplicates import content_hashes

    from batch_support import SERIAL, make_root

    root = tmp_path / "root"
    make_root(root, [1])
    found = discover(root, tmp_path / "out")[0]
    files = sorted(p for p in found.source.iterdir() if p.name != "truth.json")  # the inputs: dataset.toml and captures
    truth = {f: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
    manifest = Manifest(tmp_path / "manifest.sqlite")
    # files changed less than RACY_NS before they were hashed: their identity vouches for nothing
    assert plan_dataset(found, root, SERIAL, manifest, config_json(SERIAL)).known == {}
    monkeypatch.setattr("rotcal.batch.manifest.RACY_NS", 0)
    plan = plan_dataset(found, root, SERIAL, manifest, config_json(SERIAL))
    manifest.close()
    assert sorted(plan.known.values()) == sorted(truth.values())
    # a known digest is taken as it is (these are not the files' hashes: nothing was read) ...
    fake = {identity: "f" * 64 for identity in plan.known}
    assert {e["sha256"] for e in content_hashes(tuple(files), found.source, fake)} == {"f" * 64}
    # ... unless the file has changed since: then it is hashed again
    with files[-1].open("a") as fh:
        fh.write("\n")
    entries = content_hashes(tuple(files), found.source, fake)
    assert [e["sha256"] for e in entries] == ["f" * 64] * (len(files) - 1) + [hashlib.sha256(files[-1].read_bytes()).hexdigest()]
    # a batch's calibration.json names the inputs' true hashes, taken from its plan
    run_batch(root, tmp_path / "out", SERIAL)
    document = json.loads(next((tmp_path / "out" / "datasets").glob("*/calibration.json")).read_text())
    assert {e["path"]: e["sha256"] for e in document["inputs"]} == {
        f.name: hashlib.sha256(f.read_bytes()).hexdigest() for f in files}
