"""Expanded uncertainties with the k their degrees of freedom call for
(GUM G.4.1): on the six-pose imucal session the written and printed k are
the t quantiles (95 %) of each value's Welch-Satterthwaite dof, not 2."""

import re

import numpy as np
import polars as pl
import pytest
from scipy import stats


@pytest.mark.real
def test_few_poses_give_k_from_the_t_distribution(cli, tmp_path):
    """Twelve hand poses scattering beyond their noise: the scatter is
    estimated from 12 - 9 = 3 (or 12 - 6 = 6) residuals, so k = t(0.975, dof) > 2."""
    from posesim import hand_placed, samples_frame

    data = tmp_path / "data"
    data.mkdir()
    samples_frame(hand_placed(12, n_poses=12, samples=300, move_samples=150, excess=20.0)).write_csv(data / "poses.csv")
    (data / "dataset.toml").write_text('[device]\noutput_unit = "count"\n\n[site]\ng_local = 9.80101\ng_local_uncertainty = 0.0\n')
    code, out, err = cli("run", data, "--out", tmp_path / "out")
    assert code == 0, err
    # the rows the console prints; an orthogonal model's angles (fixed at 90 degrees) have no dof
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet").filter("recommended", pl.col("std_uncertainty") > 0)
    dof = intrinsic["dof"].to_numpy()
    k = intrinsic["coverage_factor"].to_numpy()
    # twelve positions, nine or six parameters: the excess scatter has 3 or 6 dof, and no value has more than a few dozen
    assert np.all((dof >= 3.0 - 1e-9) & (dof < 30))
    np.testing.assert_allclose(k, stats.t.ppf(0.975, dof), rtol=1e-12)
    assert k.min() > 2.2  # k = 2 would understate the 95 % interval
    np.testing.assert_allclose(intrinsic["expanded_uncertainty"].to_numpy(), k * intrinsic["std_uncertainty"].to_numpy(), rtol=1e-15)
    # what the console prints is U = k u at each value's k, e.g. s_v's
    s_v = intrinsic.filter(pl.col("parameter") == "s_v").row(0, named=True)
    printed = re.search(r"s_v\s+│[^│]+│\s+([-\d.]+) ± ([\d.]+)", out)
    assert printed is not None
    assert float(printed.group(2)) == pytest.approx(s_v["expanded_uncertainty"], rel=0.06)
    assert f"{k.min():.2f} to {k.max():.2f}" in out or (f"k = {k.min():.2f} for every value" in out and f"{k.min():.2f}" == f"{k.max():.2f}")


def test_dof_is_welch_satterthwaite_of_the_budget():
    """Hand-derived: two input groups of variances 1 and 3 with 4 and 12
    dof, and g_local (infinite dof) contributing 0 to this parameter:
    nu = 4^2 / (1/4 + 9/12) = 16."""
    from rotcal.model.results import BudgetInput, IntrinsicResult, coverage_factor

    inputs = (BudgetInput("a", "fit", 1, "x", 4.0), BudgetInput("b", "fit", 2, "y", 12.0),
              BudgetInput("g_local", "g_local", None, "", float("inf")))
    budget = {"a": np.full(9, 1.0), "b": np.full(9, 3.0), "g_local": np.zeros(9)}
    res = IntrinsicResult(0.0, np.zeros(9), np.eye(9) * 4.0, np.zeros(12), np.eye(12), budget, 9.8, 0.0, inputs, ())
    np.testing.assert_allclose(res.dof, 16.0)
    # the budget table's combined rows and the intrinsic table carry the same dof
    from rotcal.combine import intrinsic_frame
    from rotcal.metrology import budget_frame

    combined = budget_frame([res], "d", "bit").filter(pl.col("source") == "combined")["dof"].to_numpy()
    np.testing.assert_allclose(combined, 16.0)
    np.testing.assert_allclose(intrinsic_frame([res], "d", "baseline", "bit")["dof"].to_numpy(), 16.0)
    assert coverage_factor(np.array([16.0, np.inf])) == pytest.approx([2.119905299, 1.959963985])
