"""Every still interval found and not used is listed with its reason
(``still_unused.parquet``) and counted on the console: the stillness
detector's rejections (a rest too short, or too noisy: held by hand, or
shaken) and dwells no result takes."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.segment.stillness import StillnessConfig, still_and_short

from handsim import hand_session, write_session

REST, MOVE = 400, 300  # samples of a rest (4 s) and of a turn (3 s) at 100 Hz, handsim's defaults


def _shaken(seed: int, poses: tuple[int, ...], sd: float) -> pl.DataFrame:
    """A hand session of 20 rests whose rests ``poses`` carry extra white
    noise of ``sd`` counts (the session's own is 8 counts)."""
    frame, _ = hand_session(seed, n_poses=20)
    rng = np.random.default_rng(seed)
    extra = np.zeros(frame.height)
    for k in poses:
        first = k * (REST + MOVE)
        extra[first : first + REST] = 1.0
    return frame.with_columns(**{c: pl.col(c) + np.round(extra * rng.normal(0.0, sd, frame.height)) for c in "uvw"})


def test_a_shaken_rest_is_listed_and_counted(cli, tmp_path):
    """Two of 20 rests four times as noisy (32 counts beside 8): the
    detector rejects them (variance 16 times the floor, beyond its 10), and
    the run lists both as too noisy at their times, uses the other 18 and
    says so on the console."""
    frame = _shaken(3, (5, 12), 31.0)
    data = write_session(tmp_path / "data", frame)
    status, out, err = cli("run", data, "--out", tmp_path / "out")
    assert status == 0, err
    printed = " ".join((out + err).split())
    assert "2 of the 20 still intervals found are not used (still_unused.parquet lists each with its reason): 2 too noisy" in printed
    unused = pl.read_parquet(tmp_path / "out" / "still_unused.parquet")
    starts = np.round(unused["t_start_ns"].to_numpy() / 1e9, 1)
    # each listed rest lies inside the shaken one (its edges are the turns' quieter ends)
    assert np.all(np.abs(starts - np.array([5, 12]) * 7.0) <= 1.0), starts
    assert (unused["rest_s"] >= 2.0).all()
    assert unused["reason"].str.starts_with("too noisy for a rest: its samples scatter 4").all()
    assert pl.read_parquet(tmp_path / "out" / "poses.parquet").height == 18


def test_a_clean_session_lists_nothing():
    """The same session without the shaken rests: every rest used, none
    listed (the turns have a trend: they are moves, not noisy rests)."""
    frame, _ = hand_session(3, n_poses=20)
    still, rejected = still_and_short(np.round(frame["t"].to_numpy() * 1e9).astype(np.int64),
                                      frame.select("u", "v", "w").to_numpy())
    assert still.height == 20 and rejected.height == 0


def test_rests_shorter_than_the_minimum_are_listed_with_their_reason():
    """A detector told to take rests of 5 s at least finds the 4 s rests
    and lists every one as too short, none silently dropped."""
    frame, _ = hand_session(3, n_poses=6)
    still, rejected = still_and_short(np.round(frame["t"].to_numpy() * 1e9).astype(np.int64),
                                      frame.select("u", "v", "w").to_numpy(), StillnessConfig(min_dwell_s=5.0))
    assert still.height == 0 and rejected.height == 6
    assert rejected["reason"].str.starts_with("shorter than the stillness detector's minimum rest of 5 s").all()
    assert np.all(np.abs(rejected["n_samples"].to_numpy() - REST) <= 100)


def test_a_table_recording_lists_both_kinds_in_time_order():
    """The dwells a table recording's step sequences leave unused and the
    detector's rejections, in one table in time order, with one count."""
    from rotcal.combine.unreferenced import reduce_dwells
    from rotcal.segment.stillness import unused_rows
    from rotcal.tables import schema

    frame = _shaken(3, (5, 12), 31.0)
    t_ns = np.round(frame["t"].to_numpy() * 1e9).astype(np.int64)
    _, rejected = still_and_short(t_ns, frame.select("u", "v", "w").to_numpy())
    rejected = unused_rows("d", "session.csv", rejected, 0.01)
    columns = schema("dwells").polars_schema
    dwells = pl.DataFrame({"dataset": ["d"] * 4, "segment": [0, 0, 7, 9], "capture": ["session.csv"] * 4,
                           "t_start_ns": [0, 7_000_000_000, 50_000_000_000, 120_000_000_000], "dwell_s": [4.0] * 4,
                           "n_samples": [400] * 4}).with_columns(
        *(pl.lit(None, dtype).alias(name) for name, dtype in columns.items()
          if name not in ("dataset", "segment", "capture", "t_start_ns", "dwell_s", "n_samples"))
    ).select(columns.keys()).cast(columns)
    reduction = reduce_dwells(dwells, False, 9.81, 0.0, frozenset({7, 9}), rejected)
    unused = next(t.data for t in reduction.tables if t.name == "still_unused")
    assert unused["t_start_ns"].is_sorted() and unused.height == 4
    assert unused["reason"].str.starts_with("too noisy").sum() == 2
    assert unused["reason"].str.starts_with("a single pose outside every step sequence").sum() == 2
    assert reduction.warnings[0].startswith("4 of the 6 still intervals found are not used")


def test_a_refusal_says_what_was_left_out(cli, tmp_path):
    """Seven rests, two of them shaken: five poses are too few for the six
    parameters; the refusal (exit 3) counts the two left out, and their
    table is published."""
    frame, _ = hand_session(3, n_poses=7)
    rng = np.random.default_rng(3)
    extra = np.zeros(frame.height)
    for k in (2, 4):
        extra[k * (REST + MOVE) : k * (REST + MOVE) + REST] = 1.0
    frame = frame.with_columns(**{c: pl.col(c) + np.round(extra * rng.normal(0.0, 31.0, frame.height)) for c in "uvw"})
    status, out, err = cli("run", write_session(tmp_path / "data", frame), "--out", tmp_path / "out")
    assert status == 3
    assert "5 static poses" in err and "2 of the 7 still intervals found are not used" in " ".join(err.split())
    assert pl.read_parquet(tmp_path / "out" / "still_unused.parquet").height == 2
