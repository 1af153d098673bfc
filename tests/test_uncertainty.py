"""Uncertainty budget (GUM 5.1.3) and the GUM Supplement 1 Monte Carlo check
of the first-order propagation."""

import numpy as np
import polars as pl
import pytest

from rotcal.combine.labelled import SegmentCoefficients, combine_rate, linear_stage
from rotcal.config import UncertaintyConfig
from rotcal.metrology.uncertainty import budget_frame, monte_carlo, monte_carlo_frame, monte_carlo_rate, numerical_tolerance
from rotcal.model.physics import INTRINSIC

from uncertainty_coverage import reduce_dataset


@pytest.fixture(scope="module")
def reduced(make_dataset):
    return reduce_dataset(make_dataset(21))


def test_budget_adds_up_and_names_every_input(reduced):
    frame = budget_frame(reduced.results, "ds", "bit")
    assert frame.height == 5 * 9 * 5  # 5 rates x 9 parameters x (3 segments + g_local + combined)
    noise = frame.filter(pl.col("source") == "noise")
    assert sorted(set(noise["axis"])) == ["x", "y", "z"]
    # a segment's dof is its samples minus 3: 24 x 50 static samples, 4200 per rotation
    assert set(noise.filter(pl.col("rate_hz") == 0)["dof"]) == {1197.0}
    assert set(noise.filter(pl.col("rate_hz") == 0.1)["dof"]) == {4197.0}
    for res in reduced.results:
        part = frame.filter(pl.col("rate_hz") == res.rate_hz)
        total = part.filter(pl.col("source") != "combined").group_by("parameter").agg(pl.col("variance").sum())
        got = dict(total.iter_rows())
        np.testing.assert_allclose([got[p] for p in INTRINSIC], res.std_uncertainty**2, rtol=1e-12)
        combined = part.filter(pl.col("source") == "combined").sort(pl.col("parameter").replace_strict({p: i for i, p in enumerate(INTRINSIC)}))
        np.testing.assert_allclose(combined["contribution"].to_numpy(), res.std_uncertainty, rtol=1e-12)
        g_rows = part.filter(pl.col("source") == "g_local")
        # g_local enters the sensitivities only, relative u(g)/g = 3e-5 / 9.80101
        s_g = g_rows.filter(pl.col("parameter").str.starts_with("s_"))["contribution"].to_numpy()
        np.testing.assert_allclose(s_g / res.value[:3], 3e-5 / 9.80101, rtol=1e-9)
        assert np.all(g_rows.filter(~pl.col("parameter").str.starts_with("s_"))["contribution"].to_numpy() == 0)


def test_effective_dof_follows_welch_satterthwaite(reduced):
    frame = budget_frame(reduced.results, "ds", "bit").filter((pl.col("rate_hz") == 0.05) & (pl.col("parameter") == "O_v"))
    noise = frame.filter(pl.col("source") == "noise")
    u = frame.filter(pl.col("source") == "combined")["contribution"][0]
    expected = u**4 / np.sum(noise["contribution"].to_numpy() ** 4 / noise["dof"].to_numpy())
    assert frame.filter(pl.col("source") == "combined")["dof"][0] == pytest.approx(expected, rel=1e-12)
    assert 4197 < expected < 3 * 4197


def test_numerical_tolerance_is_half_a_unit_of_the_second_digit():
    np.testing.assert_allclose(numerical_tolerance(np.array([0.024087, 1.5, 0.00061])), [0.0005, 0.05, 0.000005])


def test_monte_carlo_validates_first_order_on_clean_data(reduced):
    config = UncertaintyConfig(monte_carlo=True, monte_carlo_max_draws=50_000, monte_carlo_seed=3)
    mc = monte_carlo(reduced.fits, 9.80101, 3e-5, config)
    frame = monte_carlo_frame(mc, reduced.results, "ds", "bit")
    assert frame.height == 45
    col = {c: frame[c].to_numpy() for c in frame.columns if frame[c].dtype.is_numeric()}
    np.testing.assert_allclose(col["mc_std_uncertainty"], col["std_uncertainty"], rtol=0.02)
    assert np.all(np.abs(col["mc_mean"] - col["value"]) < 0.02 * col["std_uncertainty"])
    # the S1 8.2 comparison: every interval end within tolerance or within the Monte Carlo's own noise of it
    excess = np.maximum(col["d_low"], col["d_high"]) - col["tolerance"]
    assert np.all(excess <= 3 * col["endpoint_numerical_u"])
    again = monte_carlo_frame(monte_carlo(reduced.fits, 9.80101, 3e-5, config), reduced.results, "ds", "bit")
    assert again.equals(frame)  # seeded: the same draws


def test_monte_carlo_refuses_to_validate_a_nonlinear_case():
    """Noise comparable to the signal: |r| is biased upwards (Rician) and the
    first-order interval is wrong; the linear offsets stay validated."""
    g = 9.8
    segs = []
    for k, axis in enumerate("xyz"):
        coef = np.zeros(9)
        sin_c, cos_c = [1, 0, 0][k], [2, 2, 1][k]
        for r in range(3):
            coef[3 * r + 1], coef[3 * r + 2] = -g * 10.0 * (r == sin_c), g * 10.0 * (r == cos_c)
        segs.append(SegmentCoefficients(k, axis, coef, np.eye(9) * 30.0**2))
    result = combine_rate(0.0, segs, g, 0.0)
    mc = monte_carlo_rate(linear_stage(0.0, segs), g, 0.0, np.random.default_rng(1), 100_000)
    frame = monte_carlo_frame([mc], [result], "ds", "bit")
    assert not frame.filter(pl.col("parameter").str.starts_with("s_"))["validated"].any()
    assert np.all(mc.mean[:3] > result.value[:3] + 0.3)  # 10.5 against 10.0
    assert frame.filter(pl.col("parameter").str.starts_with("O_"))["validated"].all()
