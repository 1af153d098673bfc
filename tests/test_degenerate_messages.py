"""Messages for valid but mis-described input: each names the real cause
(a sample rate no stamp can carry, a time column in another unit, more
samples than grid slots) and a library's warning becomes a note."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from rotcal import run as run_module
from rotcal.errors import InputError
from rotcal.ingest.formats.csv.reader import read_csv_capture
from rotcal.ingest.meta import load_meta
from rotcal.timebase.check import Gaps


@pytest.mark.parametrize("rate, shown", [("1e300", r"1e\+300"), ("1e-300", "1e-300")])
def test_a_sample_rate_no_stamp_can_carry_is_refused_naming_it(tmp_path, rate, shown):
    """1e300 Hz was refused as "give [format] sample_rate_hz and no time
    column" (which was given); 1e-300 Hz named a column 't' the file lacks."""
    (tmp_path / "dataset.toml").write_text(f"[format]\nsample_rate_hz = {rate}\n")
    with pytest.raises(InputError, match=rf"\[format\] sample_rate_hz = {shown} puts the samples .* apart; "
                                         r"rotcal reads rates of 1e-6 to 1e9 Hz"):
        load_meta(tmp_path / "dataset.toml")


def test_epoch_microseconds_read_as_seconds_name_time_unit_and_every_digit(tmp_path):
    """1000000000015668 was shown as "1e+15, beyond +-1e+15" (it is beyond
    9e9 s) and time_unit was not named."""
    path = tmp_path / "us.csv"
    path.write_text("t,u,v,w\n1000000000015668,1,2,3\n1000000000025668,1,2,3\n")
    with pytest.raises(InputError, match=r"column 't', row 1 is 1000000000015668, beyond ±9e\+09 s: time stamps in ms, "
                                         r"us or ns\? set dataset.toml \[format\] time_unit"):
        read_csv_capture(path, load_meta(None).csv_format, None, run_module.RunConfig().limits)


def test_more_samples_than_grid_slots_are_not_reported_as_negative_missing():
    """Stamps that jitter by half a period fill slots twice: "-104 samples
    missing (-27.5 %)" and -104 in timebase.parquet before."""
    gaps = Gaps("jitter.csv", -104, 378, 0.01, np.zeros(0, np.int64), np.zeros(0, np.int64), 0, 5)
    found, warning = gaps.findings()
    missing = next(f for f in found if f.check == "missing_samples")
    assert missing.value == 0.0 and not missing.detected
    assert warning == "jitter.csv: 104 more samples than the 378 grid slots: the stamps jitter by half a period or more"


def test_a_library_warning_during_a_run_becomes_a_note(monkeypatch, tmp_path):
    """numpy's and matplotlib's warnings reached stderr and the batch log."""
    def warn(*args):
        np.ones(1) / np.zeros(1)  # numpy's divide-by-zero RuntimeWarning
        return run_module.RunOutcome("d", "bit", (), (), ("a note",), (), None)

    monkeypatch.setattr(run_module, "_run", warn)
    with warnings.catch_warnings(record=True) as escaped:
        warnings.simplefilter("always")
        outcome = run_module.run_dataset(tmp_path, tmp_path / "out")
    assert not escaped
    assert outcome.notes[0] == "a note" and len(outcome.notes) == 2
    assert outcome.notes[1].startswith("a library warned (the result stands; tell the maintainers if it recurs): "
                                       "RuntimeWarning in test_degenerate_messages.py:")
    assert outcome.notes[1].endswith("divide by zero encountered in divide")


def test_an_integer_output_wrapping_at_2_31_is_named_not_the_pose_geometry(tmp_path):
    """Hand-placed poses whose channel u sits near 2^31 in a signed 32-bit
    output, wrapping to near -2^31 and back: "the poses are too alike ...
    near one circle" before (the jumps broke the poses apart); now the
    wrap, with the rows where it happens."""
    import polars as pl

    from rotcal.run import run_dataset

    from posesim import G_LOCAL, hand_placed, samples_frame

    sim = hand_placed(4, n_poses=12, samples=300, move_samples=100)
    wrapped = (pl.col("u").cast(pl.Int64) + 2**31 - 100 + 2**31) % 2**32 - 2**31
    path = tmp_path / "ds"
    path.mkdir()
    samples_frame(sim).with_columns(u=wrapped).write_csv(path / "session.csv")
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n')
    with pytest.raises(InputError, match=r"session.csv: column 'u' jumps from -214748\d{4} to 214748\d{4} between rows "
                                         r"\d+ and \d+: a signed 32-bit integer output wrapping around at ±2\^31"):
        run_dataset(path, tmp_path / "out")
    # an offset of 2^31 counts without a wrap is published (the offset as it is)
    samples_frame(sim).with_columns(u=pl.col("u") + 2**31).write_csv(path / "session.csv")
    run_dataset(path, tmp_path / "out2")
    offset = pl.read_parquet(tmp_path / "out2" / "intrinsic.parquet").filter(
        pl.col("recommended") & (pl.col("parameter") == "O_u"))
    assert abs(offset["value"][0] - 2**31 - sim.truth[6]) < 5 * offset["std_uncertainty"][0]
