"""The real recordings in ../shared/data/real ingest into the canonical table."""


import numpy as np
import pytest

from rotcal.ingest.dataset import load_dataset
from rotcal.segment.stillness import still_intervals

from testdata import REAL, REPO

pytestmark = pytest.mark.real


def test_jackal_mcap_ingests_all_imu_samples():
    ds = load_dataset(REAL / "jackal_mcap" / "test2_ros2.mcap")
    s = ds.samples
    assert s.height == 3061
    assert s["t_ns"].is_sorted() and s["t_ns"][0] == 47_580_000_000
    # PROVENANCE: mean acceleration (-0.018, -0.187, 9.751) m/s^2
    np.testing.assert_allclose(s.select("u", "v", "w").mean().row(0), (-0.018, -0.187, 9.751), atol=1e-3)
    assert any("/imu/data" in note for note in ds.notes)


def test_xsens_whitespace_file_without_header():
    ds = load_dataset(REAL / "imu_tk_xsens", REPO / "configs" / "imu_tk_xsens.toml")
    s = ds.samples
    assert s.height == 51175
    assert s["t_ns"][0] == 29_840_000 and s["u"][0] == 33108.0
    assert ds.meta.g_local == 9.81744


def test_xsens_static_poses_found_by_stillness():
    """Issue 5 acceptance: a plain moving-variance detector finds 38 still
    intervals (the initial rest included); 38 +- 2 is right."""
    s = load_dataset(REAL / "imu_tk_xsens", REPO / "configs" / "imu_tk_xsens.toml").samples
    intervals = still_intervals(s["t_ns"].to_numpy(), s.select("u", "v", "w").to_numpy())
    assert 36 <= intervals.height <= 40
    first = intervals.row(0, named=True)
    assert first["t_start_ns"] < 1e9 and 45e9 < first["t_end_ns"] < 55e9  # ~50 s initial rest


def test_imucal_session_with_pose_labels_and_sample_rate():
    ds = load_dataset(REAL / "imucal_session", REPO / "configs" / "imucal_session.toml")
    s = ds.samples
    assert s.height == 9414
    counts = dict(s.group_by("pose").len().iter_rows())
    assert counts == {"x_a": 1061, "x_p": 1028, "y_a": 848, "y_p": 734, "z_a": 1044, "z_p": 881, None: 3818}
    assert s["t_ns"][1] == round(1e9 / 204.8)
