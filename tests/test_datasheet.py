"""Datasheet priors (``combine.datasheet``): the bounds of ``[device]``
joined to the static fit as Type B inputs; a parameter the poses barely
determine rests on its prior, and its uncertainty never exceeds the
prior's."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from test_corpus import SUAREZ, assert_within, suarez_parameters

from rotcal.errors import InputError
from rotcal.run import run_dataset

from testdata import REPO

# MPU-6000/6050 Product Specification rev 3.4, section 6.2 (AFS_SEL = 0): 16384 LSB/g, initial calibration
# tolerance +-3 %, zero-g output +-50 mg (X, Y) and +-80 mg (Z), cross-axis sensitivity +-2 %
MPU6050 = "sensitivity = 16384\nsensitivity_tolerance = 0.03\noffset_tolerance = [819.2, 819.2, 1310.72]\n"


def _config(tmp_path, cross_axis: bool):
    text = (REPO / "configs" / "suarez_mpu6050.toml").read_text()
    text = text.replace("cross_axis = 0.02\n", ("cross_axis = 0.02\n" if cross_axis else "") + MPU6050)
    (tmp_path / "mpu6050.toml").write_text(text)
    return tmp_path / "mpu6050.toml"


def test_the_corpus_mpu6050_with_its_datasheet(tmp_path):
    """With every bound of its datasheet: the recommended (orthogonal)
    sensitivities within 0.5 % and offsets within 3 U of the authors'; the
    poses determine each better than the datasheet, and the note says so."""
    outcome = run_dataset(SUAREZ / "example_data_calibration.csv", tmp_path / "out", _config(tmp_path, True))
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet")
    assert outcome.recommended.model == "orthogonal"
    assert_within(intrinsic.filter("recommended"), suarez_parameters(), names=("s_u", "s_v", "s_w", "O_u", "O_v", "O_w"))
    assert any("every parameter they bound is determined by the poses better" in n for n in outcome.static.notes)


def test_what_the_poses_barely_determine_rests_on_the_prior(tmp_path):
    """Without the cross-axis bound the nine-parameter fit of the ten poses
    (none between u and v) leaves s_u and s_v to within about 20 %: with
    the sensitivity tolerance (3 %) their uncertainty is at most the
    prior's (u = 3 % / sqrt(3) of the nominal), they are named as resting
    on it, and s_w, which the poses determine, is not (U(s_w) 5.4 counts
    per g, a fifth of the prior's u, with its pose means widened by the
    autoregression of their residuals; 2.8 by their lag-1 and lag-2 form)."""
    outcome = run_dataset(SUAREZ / "example_data_calibration.csv", tmp_path / "out", _config(tmp_path, False))
    baseline = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet").filter(pl.col("model") == "baseline")
    rows = {r["parameter"]: r for r in baseline.iter_rows(named=True)}
    prior_u = 16384 / 9.80665 * 0.03 / np.sqrt(3)
    for name in ("s_u", "s_v"):
        u = rows[name]["std_uncertainty"]
        assert u <= prior_u, (name, u, prior_u)
    assert rows["s_w"]["expanded_uncertainty"] < 0.25 * prior_u
    assert any("s_u, s_v rest on the prior" in n for n in outcome.static.notes)
    assert abs(rows["s_w"]["value"] / suarez_parameters()[2] - 1) < 0.005


def test_a_tolerance_without_its_nominal_is_refused(tmp_path):
    text = (REPO / "configs" / "suarez_mpu6050.toml").read_text().replace("cross_axis = 0.02\n", "sensitivity_tolerance = 0.03\n")
    (tmp_path / "bad.toml").write_text(text)
    with pytest.raises(InputError, match="sensitivity_tolerance needs sensitivity"):
        run_dataset(SUAREZ / "example_data_calibration.csv", tmp_path / "out", tmp_path / "bad.toml")


def test_a_prior_the_data_contradict_is_not_joined(tmp_path):
    """The nominal of another range (8192 LSB/g, +-4 g) lies 50 % off the
    sensitivities the poses determine to 0.05 %: not joined (the results as
    without it), and the note names each with its value."""
    text = _config(tmp_path, True).read_text().replace("sensitivity = 16384", "sensitivity = 8192")
    (tmp_path / "wrong.toml").write_text(text)
    outcome = run_dataset(SUAREZ / "example_data_calibration.csv", tmp_path / "out", tmp_path / "wrong.toml")
    note = next(n for n in outcome.static.notes if n.startswith("datasheet priors"))
    assert "not joined, the data contradicting their prior beyond 3 standard uncertainties: s_u (" in note
    assert "s_v (" in note and "s_w (" in note and "O_u" not in note.split("not joined")[1]
    recommended = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet").filter("recommended")
    assert_within(recommended, suarez_parameters(), names=("s_u", "s_v", "s_w", "O_u", "O_v", "O_w"))
