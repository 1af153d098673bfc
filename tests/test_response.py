"""Frequency response against the static result (Gaitan & Geist 2021
Figs. 6 and 7): ratios and deviations with their correlations, and the
omega^2 law of a centripetal offset recovered per rotation axis."""

import numpy as np
import polars as pl
import pytest

from rotcal.combine.labelled import combine
from rotcal.metrology.response import frequency_response_frame
from rotcal.report.plot import frequency_response_png

from testdata import truth_of
from uncertainty_coverage import reduce_dataset


def test_clean_dataset_shows_no_frequency_dependence(make_dataset):
    red = reduce_dataset(make_dataset(61))
    frame = frequency_response_frame(red.results, red.fits, "ds", "bit", "baseline")
    per_rate = frame.filter(pl.col("rate_hz").is_not_null())
    assert per_rate.height == 4 * 12
    assert np.abs(per_rate["z"].to_numpy()).max() < 4.5
    slopes = frame.filter(pl.col("quantity") == "offset_omega2_slope")
    assert slopes.height == 12 and np.abs(slopes["z"].to_numpy()).max() < 4.5
    assert slopes["p_value"].min() > 1e-4


def test_sensitivity_ratio_is_free_of_g_local_and_uses_the_noise_only(make_dataset):
    red = reduce_dataset(make_dataset(61))
    precise = frequency_response_frame(red.results, red.fits, "ds", "bit", "baseline")
    vague_g = combine(red.fits, 9.80101, 3e-3)  # 100 times the uncertainty of g_local
    vague = frequency_response_frame(vague_g, red.fits, "ds", "bit", "baseline")
    ratio = pl.col("quantity") == "sensitivity_ratio"
    np.testing.assert_allclose(vague.filter(ratio)["std_uncertainty"], precise.filter(ratio)["std_uncertainty"], rtol=1e-6)
    # while the sensitivities themselves become 20 times less certain
    assert vague_g[1].std_uncertainty[0] > 10 * red.results[1].std_uncertainty[0]
    by_rate = {r.rate_hz: r for r in red.results}
    row = precise.filter(ratio & (pl.col("rate_hz") == 0.1) & (pl.col("parameter") == "s_w")).row(0, named=True)
    f, dc = by_rate[0.1], by_rate[0.0]
    u_f, u_0 = np.sqrt(f.noise_cov[2, 2]), np.sqrt(dc.noise_cov[2, 2])
    q = f.value[2] / dc.value[2]
    assert row["value"] == pytest.approx(q, rel=1e-14)
    assert row["std_uncertainty"] == pytest.approx(q * np.hypot(u_f / f.value[2], u_0 / dc.value[2]), rel=1e-6)


def test_centripetal_slope_per_axis_is_minus_r_dot_d(make_dataset):
    path = make_dataset(62, effects=("centripetal:axis=x,radius_m=0.2",))
    truth = truth_of(path)
    d = np.array([truth["effects"][0]["parameters"].get(f"d_{s}_m", 0.0) for s in "xyz"])
    resp = np.array(truth["dut"]["responsivity"])
    red = reduce_dataset(path)
    frame = frequency_response_frame(red.results, red.fits, "ds", "bit", "baseline")
    slopes = frame.filter(pl.col("quantity") == "offset_omega2_slope")
    x = slopes.filter(pl.col("axis") == "x").sort("parameter")
    expected = -resp @ d  # output change -w^2 r.d (docs/effects.md)
    assert np.all(np.abs(x["value"].to_numpy() - expected) < 4 * x["std_uncertainty"].to_numpy())
    assert x["p_value"].min() > 1e-4  # the omega^2 law holds
    others = slopes.filter(pl.col("axis").is_in(["y", "z"]))
    assert np.abs(others["z"].to_numpy()).max() < 4.5
    accel = frame.filter((pl.col("quantity") == "acceleration_omega2_slope") & (pl.col("axis") == "x")).sort("parameter")
    np.testing.assert_allclose(accel["value"], -(resp / np.linalg.norm(resp, axis=1)[:, None]) @ d, atol=4 * accel["std_uncertainty"].max())
    v_change = frame.filter((pl.col("quantity") == "centripetal_acceleration") & (pl.col("parameter") == "O_v")
                            & (pl.col("rate_hz") == 0.5))
    assert v_change["z"][0] < -100  # Fig. 7: a large offset change at 0.5 Hz


def test_png_is_written_deterministically(make_dataset, tmp_path):
    red = reduce_dataset(make_dataset(61))
    frame = frequency_response_frame(red.results, red.fits, "ds", "bit", "baseline")
    first = frequency_response_png(frame, tmp_path / "a.png", "ds")
    second = frequency_response_png(frame, tmp_path / "b.png", "ds")
    data = first.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data == second.read_bytes()
    assert not list(tmp_path.glob(".*.tmp"))
    assert frequency_response_png(frame.clear(), tmp_path / "c.png", "ds") is None
