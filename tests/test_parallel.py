"""One rule for the cores rotcal uses (``rotcal.parallel``), and the fit
stage, the MCAP reader and the batch pool each keeping to it."""

import threading

import pytest

from rotcal import parallel
from rotcal.batch.runner import run_batch
from rotcal.config import BatchConfig, FitConfig, Limits, RunConfig
from rotcal.fit import segments
from rotcal.ingest.formats.mcap import fast as mcap_fast

from batch_support import SERIAL, make_root


@pytest.fixture
def four_cores(monkeypatch):
    """A process allowed on 4 cores, whatever the machine has."""
    monkeypatch.setattr(parallel, "available_cores", lambda: 4)


def test_the_rule(four_cores):
    assert parallel.cores(0) == 4 and parallel.cores(1) == 1 and parallel.cores(6) == 6
    assert parallel.share(0, 4) == 1 and parallel.share(0, 1) == 4 and parallel.share(2, 8) == 1 and parallel.share(6, 2) == 3


def test_available_cores_follow_the_affinity():
    if not hasattr(parallel.os, "sched_getaffinity"):
        pytest.skip("no CPU affinity on this platform")
    assert parallel.available_cores() == len(parallel.os.sched_getaffinity(0))


class _Pool:
    """Stands for ThreadPoolExecutor: records its size, runs in this thread."""

    sizes: list[int] = []

    def __init__(self, size):
        _Pool.sizes.append(size)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return None

    def map(self, fn, *iterables):
        return map(fn, *iterables)


@pytest.mark.parametrize("workers, pools", [(0, [4]), (2, [2]), (1, [])])
def test_mcap_reader_decompresses_on_the_cores_given(make_dataset, monkeypatch, four_cores, workers, pools):
    monkeypatch.setattr(mcap_fast, "ThreadPoolExecutor", _Pool)
    _Pool.sizes = []
    capture = sorted(make_dataset(1, fmt="mcap-cdr").glob("*.mcap"))[0]
    before = threading.active_count()
    topics = mcap_fast.read_topics(capture, {"/imu"}, Limits(), workers)
    assert _Pool.sizes == pools and threading.active_count() == before
    assert topics["/imu"].count > 0


@pytest.mark.parametrize("workers, pools", [(0, [4]), (3, [3]), (1, [])])
def test_fit_stage_threads_on_the_cores_given(monkeypatch, four_cores, workers, pools):
    import numpy as np
    import polars as pl

    monkeypatch.setattr(segments, "ThreadPoolExecutor", _Pool)
    monkeypatch.setattr(segments, "THREADED_MIN_SAMPLES", 0)
    _Pool.sizes = []
    n = 1000
    theta = np.tile(np.linspace(0, 360, n, endpoint=False), 6)
    samples = pl.DataFrame({"segment": np.repeat(np.arange(6), n), "t_ns": np.arange(6 * n) * 60_000_000, "angle_deg": theta,
                            **{c: np.sin(np.radians(theta)) for c in ("u", "v", "w")}})
    table = pl.DataFrame({"segment": range(6), "kind": ["rotation"] * 6, "axis": ["z"] * 6, "rate_hz": [0.5] * 6,
                          "angle_source": ["commanded"] * 6})
    fits = segments.fit_segments(samples, table, FitConfig(), workers)
    assert _Pool.sizes == pools and [f.segment for f in fits] == list(range(6))


@pytest.mark.parametrize("batch_workers, datasets, run_cores", [(1, 1, 1), (0, 1, 4)])
def test_batch_gives_each_run_its_share(tmp_path, monkeypatch, four_cores, batch_workers, datasets, run_cores):
    seen = []

    def record(path, out, meta, config, known=None):
        seen.append(config.run.workers)
        raise RuntimeError("recorded")

    monkeypatch.setattr("rotcal.run.run_dataset", record)
    make_root(tmp_path / "root", range(1, datasets + 1))
    config = RunConfig(diagnosis=SERIAL.diagnosis, batch=BatchConfig(workers=batch_workers))
    run_batch(tmp_path / "root", tmp_path / "out", config)
    assert seen == [run_cores] * datasets
