"""Degenerate recordings beside the fuzzer (docs/fuzzing.md, "Degenerate
recordings"): hypothesis draws valid recordings and makes them degenerate
(``scripts/degenerate_inputs.py``); each must be refused in one line or
give results within their uncertainties of the truth, with no finding the
degeneration alone produced. A short run here; ``scripts/degenerate.py``
is the long one. Then MCAP files whose chunks and channels are unusual:
every message read, on any thread count, as the official reader reads it.
"""

from __future__ import annotations

import faulthandler
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from rotcal.config import Limits
from rotcal.ingest.formats.mcap import reader as mcap_source
from rotcal.ingest.meta import load_meta

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import degenerate_inputs  # noqa: E402
from test_degenerate_mcap import _definitions_chunk, _empty_chunk, _imu_capture, _rebuilt, _split_capture  # noqa: E402

PROPERTY = settings(max_examples=10, deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
HOLDING_TABLE_KINDS = degenerate_inputs.TABLE_KINDS


@PROPERTY
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(degenerate_inputs.STATIC_KINDS))
def test_degenerate_static_recordings_keep_the_invariant(tmp_path_factory, seed, kind):
    where = tmp_path_factory.mktemp("static")
    drawn = degenerate_inputs.static_recording(np.random.default_rng(seed), kind, where / "ds")
    assert degenerate_inputs.violation(drawn, where / "out") is None, (drawn.kind, drawn.detail)


@settings(PROPERTY, max_examples=4)
@given(seed=st.integers(0, 2**32 - 1), kind=st.sampled_from(HOLDING_TABLE_KINDS))
def test_degenerate_table_recordings_keep_the_invariant(tmp_path_factory, seed, kind):
    where = tmp_path_factory.mktemp("table")
    drawn = degenerate_inputs.table_recording(np.random.default_rng(seed), kind, where / "ds")
    assert degenerate_inputs.violation(drawn, where / "out") is None, (drawn.kind, drawn.detail)


@pytest.fixture(scope="module")
def imu_capture(tmp_path_factory) -> Path:
    return _imu_capture(tmp_path_factory.mktemp("imu") / "imu.mcap")


@settings(PROPERTY, max_examples=6)
@given(inserted=st.lists(st.sampled_from(["empty", "empty-zstd", "definitions"]), min_size=1, max_size=4),
       workers=st.integers(1, 4))
def test_empty_and_definition_only_chunks_lose_no_message(tmp_path_factory, imu_capture, inserted, workers):
    chunks = {"empty": lambda: _empty_chunk(""), "empty-zstd": lambda: _empty_chunk("zstd"),
              "definitions": _definitions_chunk}
    path = _rebuilt(imu_capture, tmp_path_factory.mktemp("chunks") / "inserted.mcap", [chunks[k]() for k in inserted])
    faulthandler.dump_traceback_later(120, exit=True)  # a deadlock ends the run with every thread's stack, not a hang
    try:
        frame, _ = mcap_source.read_mcap_capture(path, load_meta(None), None, Limits(), workers)
    finally:
        faulthandler.cancel_dump_traceback_later()
    assert frame.height == sum(1 for _ in make_reader(path.open("rb")).iter_messages(topics=["/imu"]))


@settings(PROPERTY, max_examples=4)
@given(workers=st.integers(1, 4))
def test_a_topic_over_two_channels_loses_no_message(tmp_path_factory, workers):
    path = _split_capture(tmp_path_factory.mktemp("split") / "split.mcap")
    frame, _ = mcap_source.read_mcap_capture(path, load_meta(None), None, Limits(), workers)
    assert frame.height == sum(1 for _ in make_reader(path.open("rb")).iter_messages(topics=["/imu"]))
