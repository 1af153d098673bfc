"""The table channel's labels (``mcap_table.table_labels``) against the
per-sample formulas of docs/inputs.md, written out here sample by sample:
the label in force is the last message at or before the sample; within a
run (same axis and rate) the angle is interpolated towards the next
message's, unwrapped with the commanded rate; after a run's last message it
is extrapolated at the rate; at rest it is held. Bit for bit, over several
blocks of samples, with samples before the first message, repeated message
times, runs of one message and held angles of -0.0."""

import numpy as np
import pytest

from rotcal.ingest.formats.mcap import table as mcap_table
from rotcal.ingest.formats.mcap.table import TableTrack, table_labels


def _expected(t_ns: np.ndarray, track: TableTrack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each sample's (axis code, rate, angle) from the formulas, one sample at a time."""
    m = track.t_ns.size
    axis, rate, angle = np.full(t_ns.size, -1), np.full(t_ns.size, np.nan), np.full(t_ns.size, np.nan)
    for k, t in enumerate(t_ns.tolist()):
        i = int(np.searchsorted(track.t_ns, t, side="right")) - 1
        if i < 0:
            continue
        a, r, t_i = float(track.angle_deg[i]), float(track.rate_hz[i]), int(track.t_ns[i])
        axis[k], rate[k] = track.axis[i], r
        same_run = i + 1 < m and track.axis[i + 1] == track.axis[i] and track.rate_hz[i + 1] == r
        if r == 0:
            angle[k] = a
        elif same_run:
            span = int(track.t_ns[i + 1]) - t_i
            expected = 360.0 * r * span / 1e9
            increment = expected + (float(track.angle_deg[i + 1]) - a - expected + 180.0) % 360.0 - 180.0
            angle[k] = a + (t - t_i) / span * increment
        else:
            angle[k] = a + 360.0 * r * (t - t_i) / 1e9
    return axis, rate, angle


@pytest.fixture
def case():
    rng = np.random.default_rng(7)
    m = 3000
    t_msg = np.sort(rng.integers(10**9, 10**9 + 80 * 10**9, m))
    t_msg[100:103] = t_msg[100]  # repeated message times
    run = np.repeat(np.arange(900), rng.integers(1, 20, 900))[:m]  # runs of 1 to 19 messages
    rate = np.where(run % 3 == 0, 0.0, np.round(rng.uniform(-2, 2, 900)[run], 3))
    axis = (run % 3).astype(np.int8)
    angle = rng.uniform(-720, 720, m)
    angle[rate == 0] = np.where(rng.random(int((rate == 0).sum())) < 0.5, -0.0, 90.0)
    track = TableTrack(t_msg, axis, rate, angle)
    t_ns = np.sort(rng.integers(5 * 10**8, 10**9 + 82 * 10**9, 3 * mcap_table._LABEL_BLOCK + 123))
    t_ns[:50] = np.arange(50) + 10**8  # before the first message
    t_ns[7000:7010] = t_msg[100]  # on the repeated time
    return np.sort(t_ns), track  # in time order, as ingest gives them


@pytest.mark.parametrize("workers", [1, 2, 3])  # the blocks shared out over threads
def test_labels_follow_the_formulas_bit_for_bit(case, workers):
    t_ns, track = case
    frame = table_labels(t_ns, track, workers)
    axis, rate, angle = _expected(t_ns, track)
    codes = frame["axis"].to_physical().fill_null(-1).to_numpy()
    np.testing.assert_array_equal(codes, axis)
    np.testing.assert_array_equal(frame["rate_hz"].fill_null(np.nan).to_numpy().view(np.int64), rate.view(np.int64))
    got = frame["angle_deg"].fill_null(np.nan).to_numpy()
    np.testing.assert_array_equal(got.view(np.int64), angle.view(np.int64))  # -0.0 held as -0.0
    assert np.isnan(got[:50]).all() and (np.signbit(got) & (got == 0)).any()


@pytest.mark.parametrize("block", [3, 4, 1 << 15])
def test_samples_on_message_times_take_the_last_message_at_that_time(monkeypatch, block):
    """A sample stamped at a message's time is under that message (the last
    of several at one time), also where a block of samples starts or ends
    on it; distinct rates and axes make any other message visible."""
    monkeypatch.setattr(mcap_table, "_LABEL_BLOCK", block)
    track = TableTrack(np.array([10, 20, 20, 30, 40]), np.array([0, 1, 2, 0, 1], np.int8),
                       np.array([0.5, 0.25, 0.125, 0.0, 2.0]), np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    t_ns = np.array([5, 10, 15, 20, 20, 25, 30, 30, 35, 40, 45])
    frame = table_labels(t_ns, track, 2)
    axis, rate, angle = _expected(t_ns, track)
    np.testing.assert_array_equal(frame["axis"].to_physical().fill_null(-1).to_numpy(), axis)
    np.testing.assert_array_equal(frame["rate_hz"].fill_null(np.nan).to_numpy(), rate)
    np.testing.assert_array_equal(frame["angle_deg"].fill_null(np.nan).to_numpy(), angle)
    assert frame["rate_hz"].to_list()[3:5] == [0.125, 0.125]
