"""Expanded uncertainties with the k their degrees of freedom call for
(GUM G.4.1): on the six-pose imucal session the written and printed k are
the t quantiles (95 %) of each value's Welch-Satterthwaite dof, not 2."""

import re

import numpy as np
import polars as pl
import pytest
from scipy import stats

from testdata import REAL, REPO


@pytest.mark.real
def test_six_poses_give_k_from_the_t_distribution(cli, tmp_path):
    code, out, err = cli("run", REAL / "imucal_session", "--meta", REPO / "configs" / "imucal_session.toml", "--out", tmp_path)
    assert code == 0, err
    intrinsic = pl.read_parquet(tmp_path / "intrinsic.parquet").filter(pl.col("model") == "baseline")
    dof = intrinsic["dof"].to_numpy()
    k = intrinsic["coverage_factor"].to_numpy()
    # six positions, 12-parameter fit: the residual dof is 6, and no value has more than a few dozen
    assert np.all((dof >= 6.0 - 1e-9) & (dof < 30))
    np.testing.assert_allclose(k, stats.t.ppf(0.975, dof), rtol=1e-12)
    assert k.min() > 2.2  # k = 2 would understate the 95 % interval
    np.testing.assert_allclose(intrinsic["expanded_uncertainty"].to_numpy(), k * intrinsic["std_uncertainty"].to_numpy(), rtol=1e-15)
    # what the console prints is U = k u at each value's k, e.g. s_v's
    s_v = intrinsic.filter(pl.col("parameter") == "s_v").row(0, named=True)
    printed = re.search(r"s_v\s+│[^│]+│\s+([-\d.]+) ± ([\d.]+)", out)
    assert printed is not None
    assert float(printed.group(2)) == pytest.approx(s_v["expanded_uncertainty"], rel=0.06)
    assert f"{k.min():.2f} to {k.max():.2f}" in out


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
