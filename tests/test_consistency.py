"""Geist 2017 section 3 consistency checks: the two estimates of each
component and the three of each offset, tested against their uncertainties."""

import numpy as np
import polars as pl
from scipy.stats import chi2 as chi2_dist

from rotcal.metrology.consistency import FAMILY_ALPHA, consistency_frame, consistency_note

from uncertainty_coverage import reduce_dataset


def test_clean_dataset_is_consistent_and_statistics_add_up(make_dataset):
    red = reduce_dataset(make_dataset(41))
    frame = consistency_frame(red.fits, 9.80101, "ds", "bit", "baseline")
    assert frame.height == 5 * 12
    assert frame["consistent"].all() and consistency_note(frame) is None
    assert frame["alpha"][0] == FAMILY_ALPHA / 60
    comp = frame.filter(pl.col("component") != "")
    assert set(comp["dof"]) == {1} and set(frame.filter(pl.col("component") == "")["dof"]) == {2}
    # Eq. 9's pairing: x components from the y and z rotations, y from x and z, z from x and y
    sources = dict(comp.filter(pl.col("rate_hz") == 0.1).select("quantity", "source_axes").iter_rows())
    assert sources["u_x"] == "y,z" and sources["v_y"] == "x,z" and sources["w_z"] == "x,y"
    np.testing.assert_allclose(comp["z"].to_numpy() ** 2, comp["chi2"].to_numpy(), rtol=1e-10)
    row = frame.filter((pl.col("rate_hz") == 0.05) & (pl.col("quantity") == "O_w")).row(0, named=True)
    x, u = np.array(row["estimates"]), np.array(row["std_uncertainties"])
    w = 1 / u**2
    mean = np.sum(w * x) / w.sum()
    assert abs(row["weighted_mean"] - mean) < 1e-12 * abs(mean)
    assert abs(row["std_uncertainty"] - w.sum() ** -0.5) < 1e-12
    assert abs(row["chi2"] - np.sum(w * (x - mean) ** 2)) < 1e-9
    assert abs(row["p_value"] - chi2_dist.sf(row["chi2"], 2)) < 1e-12
    # the component estimates are in output unit per m/s^2 and match the combination
    res = {r.rate_hz: r for r in red.results}[0.05]
    np.testing.assert_allclose(comp.filter(pl.col("rate_hz") == 0.05)["weighted_mean"], res.responsivity.ravel(), rtol=1e-12)


def test_centripetal_offsets_disagree_and_components_do_not(make_dataset):
    """A sensing point 0.1 m off the x axis shifts the offsets of the x
    rotations by -w^2 r.d: at 0.5 Hz about 1000 output units on v."""
    red = reduce_dataset(make_dataset(42, effects=("centripetal:axis=x,radius_m=0.1",)))
    frame = consistency_frame(red.fits, 9.80101, "ds", "bit", "baseline")
    fast = frame.filter((pl.col("rate_hz") >= 0.1) & (pl.col("component") == ""))
    assert not fast.filter(pl.col("channel") != "u")["consistent"].any()
    assert frame.filter(pl.col("component") != "")["consistent"].all()
    assert frame.filter(pl.col("rate_hz") == 0)["consistent"].all()  # static steps have no centripetal term
    note = consistency_note(frame)
    assert note is not None and "consistency.parquet" in note


def test_statistics_of_checks_of_several_sizes_by_hand():
    """Two estimates 1 and 3 (u = 1): mean 2, u 1/sqrt(2), chi^2 2, z -sqrt(2);
    three 0, 3, 6 with u 1, 1, 2: weights 1, 1, 1/4, mean 4.5/2.25 = 2,
    chi^2 4 + 1 + 16/4 = 9; one noise-free pair: its plain mean, no statistic."""
    from rotcal.metrology.consistency import _statistics

    x = [np.array([1.0, 3.0]), np.array([0.0, 3.0, 6.0]), np.array([4.0, 5.0])]
    u = [np.array([1.0, 1.0]), np.array([1.0, 1.0, 2.0]), np.array([0.0, 0.0])]
    mean, u_mean, chi2, z = _statistics(x, u)
    np.testing.assert_allclose(mean, [2.0, 2.0, 4.5], rtol=1e-15)
    np.testing.assert_allclose(u_mean, [np.sqrt(0.5), np.sqrt(1 / 2.25), 0.0], rtol=1e-15)
    np.testing.assert_allclose(chi2[:2], [2.0, 9.0], rtol=1e-15)
    assert np.isnan(chi2[2])
    np.testing.assert_allclose(z[0], -np.sqrt(2.0), rtol=1e-15)
    assert np.isnan(z[1]) and np.isnan(z[2])
