"""Held-out comparison of nested models (``combine.heldout``): the PRESS
residuals against explicit leave-one-out refits, the paired test against
scipy.stats, and the recommendations it gates on real recordings."""

from __future__ import annotations

import numpy as np
import polars as pl
from scipy import stats
from test_corpus import SUAREZ, assert_within, suarez_parameters

from rotcal.combine.heldout import compare, press
from rotcal.combine.posemodels import choose_model
from rotcal.run import run_dataset

from testdata import REPO


def test_press_is_the_explicit_leave_one_out_refit():
    """For a linear least-squares fit, PRESS is exact: each pose's
    prediction error equals that of the fit to the other poses, for poses
    of one residual and of three (the block form)."""
    rng = np.random.default_rng(3)
    for size in (1, 3):
        n = 12
        design = rng.standard_normal((n * size, 4))
        y = design @ rng.standard_normal(4) + rng.standard_normal(n * size)
        coef = np.linalg.lstsq(design, y, rcond=None)[0]
        explicit = []
        for k in range(n):
            keep = np.ones(n * size, bool)
            keep[k * size:(k + 1) * size] = False
            other = np.linalg.lstsq(design[keep], y[keep], rcond=None)[0]
            explicit.append(float(np.sum((y[~keep] - design[~keep] @ other) ** 2)))
        np.testing.assert_allclose(press(y - design @ coef, design, size), explicit, rtol=1e-9)


def test_the_paired_test_is_students_on_the_log_ratios():
    """The one-sided p-value is scipy's paired t test's on ln(1 + error);
    one pose predicted far better does not swamp fifteen predicted better,
    nor does one predicted far worse hide fifteen predicted worse."""
    rng = np.random.default_rng(4)
    simple, rich = rng.gamma(2.0, size=15) + 0.3, rng.gamma(2.0, size=15)
    held = compare(simple, rich)
    expected = stats.ttest_rel(np.log1p(simple), np.log1p(rich), alternative="greater")
    assert held.dof == 14 and held.wins == int(np.sum(simple > rich))
    np.testing.assert_allclose([held.t, held.p_value], [expected.statistic, expected.pvalue], rtol=1e-9)
    better = np.r_[np.full(15, 2.0), 1000.0] + rng.uniform(0, 0.1, 16)
    assert compare(better, np.ones(16)).better
    assert not compare(np.ones(16), better).better


def test_the_corpus_mpu6050_recommends_what_predicts(tmp_path):
    """The MPU-6050's ten poses (none between u and v) with its datasheet's
    cross-axis bound (2 %): the F test rejects orthogonal axes against
    the noise alone, but the nine parameters predict no held-out pose better,
    so the orthogonal model is recommended, within 0.5 % and 3 U of the
    authors; the nine-parameter phi_uv rests on the prior (U under 3
    degrees, not 140), and the recommended model predicts held-out poses no
    worse than the nine-parameter baseline."""
    outcome = run_dataset(SUAREZ / "example_data_calibration.csv", tmp_path, REPO / "configs" / "suarez_mpu6050.toml")
    intrinsic = pl.read_parquet(tmp_path / "intrinsic.parquet")
    assert outcome.recommended.model == "orthogonal" and "left out one pose at a time" in outcome.recommended.reason
    assert "left out one pose at a time, the nine-parameter model does not predict" in (tmp_path / "calibration.json").read_text()
    recommended = intrinsic.filter("recommended")
    assert_within(recommended, suarez_parameters(), names=("s_u", "s_v", "s_w", "O_u", "O_v", "O_w"))
    phi_uv = intrinsic.filter(pl.col("model") == "baseline", pl.col("parameter") == "phi_uv")
    assert phi_uv["expanded_uncertainty"][0] < 3.0
    choice = choose_model(outcome.static.positions, outcome.results[0].g_local, 0.0, 0.0115, 0.02 / np.sqrt(3))
    assert choice.heldout is not None and choice.heldout.simple <= choice.heldout.rich


def test_jig_positions_keep_the_twelve_parameters_where_they_predict():
    """16 jig positions of random orientation, phi_uv = 90.5 degrees: the
    12-parameter model is chosen, the F test and the held-out comparison
    both in its reason; the same positions of an orthogonal DUT keep the
    orthogonal model."""
    from rotcal.combine.refmodels import choose_reference_model

    from posesim import G_LOCAL, hand_placed, reference_pose_table

    d = np.random.default_rng(1).standard_normal((16, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    skewed = choose_reference_model(reference_pose_table(hand_placed(3, directions=d, angles_deg=(90.5, 90, 90)), d), G_LOCAL, 0.0)
    assert skewed.chosen == "baseline" and skewed.heldout is not None and skewed.heldout.better
    assert "left out one pose at a time, the 12-parameter model predicts the held-out poses better" in skewed.reason
    square = choose_reference_model(reference_pose_table(hand_placed(3, directions=d, angles_deg=(90, 90, 90)), d), G_LOCAL, 0.0)
    assert square.chosen == "orthogonal"
