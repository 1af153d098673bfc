"""Issue 16, item 2: a dataset of plain CSV captures is read in one parse
(``ingest.csv_joined``) and gives the per-file reader's samples bit for bit;
anything the joined read does not cover, and every fault, goes to the
per-file reader, which words it as before."""

import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest

import rotcal.ingest.dataset as ingest
from rotcal.errors import InputError
from rotcal.ingest.dataset import load_dataset
from rotcal.simulate import Plan, SimulationSpec

SMALL = SimulationSpec(plan=Plan(rates_hz=(0.1,), rotation_samples=600, step_samples=10))
HEADER = "t,u,v,w,axis,rate_hz,angle_deg\n"


@pytest.fixture
def joined_calls(monkeypatch):
    """Each ``read_joined`` result: None where the per-file reader read the dataset."""
    calls: list = []
    real = ingest.read_joined

    def spy(*args):
        calls.append(real(*args))
        return calls[-1]

    monkeypatch.setattr(ingest, "read_joined", spy)
    return calls


def per_file(path: Path, monkeypatch) -> pl.DataFrame:
    """The samples as the reader of one capture at a time gives them (the reference)."""
    with monkeypatch.context() as m:
        m.setattr(ingest, "read_joined", lambda *args: None)
        return load_dataset(path).samples


def same_bits(a: pl.DataFrame, b: pl.DataFrame) -> None:
    assert a.schema == b.schema and a.height == b.height
    for name in a.columns:
        left, right = a[name], b[name]
        if left.dtype == pl.Float64:  # the bits: -0.0 and 0.0 differ, NaN equals itself
            assert np.array_equal(left.to_numpy().view(np.int64), right.to_numpy().view(np.int64)), name
        else:
            assert left.cast(pl.String).to_list() == right.cast(pl.String).to_list(), name


def test_simulated_dataset_is_joined_with_the_per_file_samples(make_dataset, joined_calls, monkeypatch):
    path = make_dataset(1, spec=SMALL)
    samples = load_dataset(path).samples
    assert joined_calls and joined_calls[0] is not None
    same_bits(samples, per_file(path, monkeypatch))
    assert samples["capture"].n_unique() == len(list(path.glob("*.csv")))


def test_hand_written_captures(tmp_path, joined_calls, monkeypatch):
    """Two captures given in reverse time order, one with -0 and a row
    without labels: times to the nanosecond, sorted across captures, each
    sample named by its file, the sign of zero kept."""
    (tmp_path / "a.csv").write_text(HEADER + "2.0,-0,1,2,x,0.1,5\n2.5,3,4,5,,,\n")
    (tmp_path / "b.csv").write_text(HEADER + "1.0,7,8,9,y,0,0\n3.0,1,1,1,y,0,0")  # no final newline
    samples = load_dataset(tmp_path).samples
    assert joined_calls[0] is not None
    assert samples["t_ns"].to_list() == [1_000_000_000, 2_000_000_000, 2_500_000_000, 3_000_000_000]
    assert samples["capture"].cast(pl.String).to_list() == ["b.csv", "a.csv", "a.csv", "b.csv"]
    assert samples["u"].to_list() == [7.0, 0.0, 3.0, 1.0] and np.signbit(samples["u"][1])
    assert samples["label_source"].to_list() == ["file", "file", None, "file"]
    same_bits(samples, per_file(tmp_path, monkeypatch))


@pytest.mark.parametrize("damage, message", [
    (lambda text: text.replace("\n", "\n\n", 3), None),  # blank lines: skipped by the per-file reader
    (lambda text: text.replace(HEADER, "# logger 7\n" + HEADER), None),  # a comment line
    (lambda text: text.replace("t,u,v", "t, u, v"), None),  # a header with blanks
    (lambda text: text.replace("\n", "\r\n"), None),  # CRLF line ends
    (lambda text: text.replace(",x,", ",X,", 1), None),  # a label in capitals: made lower case
    (lambda text: text.replace(",x,", ",q,", 1), "unknown axis label 'q' at row 1 "),
    (lambda text: "\n".join(text.split("\n")[:3] + text.split("\n")[4:5] + text.split("\n")[3:4] + text.split("\n")[5:]),
     "time goes backwards at row 4"),
])
def test_what_the_joined_read_does_not_cover_goes_to_the_per_file_reader(dataset_copy, joined_calls, monkeypatch,
                                                                         damage, message):
    rotation = sorted(dataset_copy.glob("*_0.1hz.csv"))[0]
    rotation.write_text(damage(rotation.read_text()))
    if message is None:
        samples = load_dataset(dataset_copy).samples
        assert joined_calls[0] is None
        same_bits(samples, per_file(dataset_copy, monkeypatch))
        return
    with pytest.raises(InputError, match=message) as caught:
        load_dataset(dataset_copy)
    assert joined_calls[0] is None and rotation.name in str(caught.value)


def test_a_step_back_beyond_the_range_of_a_difference_is_refused(tmp_path, joined_calls):
    """From +9e9 s to -9e9 s: the difference of the stamps, -1.8e19 ns,
    would wrap to a positive int64; the step back is still found."""
    (tmp_path / "a.csv").write_text(HEADER + "3,1,2,3,x,0,0\n9e9,1,2,3,x,0,0\n-9e9,1,2,3,x,0,0\n5,1,2,3,x,0,0\n")
    (tmp_path / "b.csv").write_text(HEADER + "4,1,2,3,x,0,0\n")  # before a.csv's end: the samples are sorted
    with pytest.raises(InputError, match="a.csv: time goes backwards at row 3"):
        load_dataset(tmp_path)
    assert joined_calls[0] is None


@pytest.fixture
def dataset_copy(make_dataset, tmp_path):
    dst = tmp_path / "dut"
    shutil.copytree(make_dataset(1, spec=SMALL), dst)
    return dst
