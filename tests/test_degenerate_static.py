"""Static recordings that are valid but degenerate: a dead, stuck or
saturated channel, outputs quantized coarsely (identical samples in a
pose), against hand-derived values and the simulated truth."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest

from rotcal.errors import UndeterminedError
from rotcal.fit.means import group_statistics
from rotcal.fit.quantization import mean_rounding_variance, output_step
from rotcal.run import run_dataset

from posesim import G_LOCAL, HAND_POSES, hand_placed


def _jig_dataset(path, y: np.ndarray, sim) -> object:
    reference = sim.directions[sim.pose]
    path.mkdir()
    pl.DataFrame({"t": sim.t_ns / 1e9, **{c: y[:, r] for r, c in enumerate("uvw")},
                  **{c: reference[:, r] for r, c in enumerate(("gx", "gy", "gz"))}}).write_csv(path / "positions.csv")
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n'
                                       "g_local_uncertainty = 0.0\n")
    return path


@pytest.fixture(scope="module")
def jig():
    return hand_placed(4, n_poses=12, samples=100)


@pytest.mark.parametrize("fault, expected", [
    ("dead", "channel w reads 0 in every one of the 12 poses (dead, stuck or disconnected)"),
    ("stuck", "channel w reads 1234 in every one of the 12 poses (dead, stuck or disconnected)"),
    ("saturated", "channel u reads 32767 without scatter in 6 of the 12 poses, where gravity's projection differs between "
                  "them (saturated at its limit)")])
def test_a_dead_stuck_or_saturated_channel_is_refused_with_the_reason(jig, tmp_path, fault, expected):
    """With jig references: a LinAlgError (dead), s_w = 4.6e-13 (stuck) or a
    published result (saturated) before; now one line saying why."""
    y = jig.y.copy()
    if fault == "saturated":
        y[:, 0] = np.minimum(y[:, 0] * 20, 32767)
    else:
        y[:, 2] = 0 if fault == "dead" else 1234
    with pytest.raises(UndeterminedError, match=expected.replace("(", r"\(").replace(")", r"\)")):
        run_dataset(_jig_dataset(tmp_path / fault, y, jig), tmp_path / "out")


@pytest.mark.parametrize("seed, step", [(1, 100.0), (2, 100.0), (2, 1000.0)])
def test_six_faces_quantized_coarsely_keep_the_truth_within_their_uncertainty(tmp_path, seed, step):
    """The six faces with outputs rounded to multiples of 100 or 1000
    counts (noise 1 count): every pose's samples are identical. Before,
    the rounding was taken as independent from sample to sample with a
    step of one count: offsets 1,000 to 1e14 u from the truth. Now the
    step is found (the levels' common divisor) and each pose mean carries
    it: every fitted parameter within 3 u of the truth, no effect found."""
    sim = hand_placed(seed, samples=100, noise=1.0, directions=HAND_POSES[:6])
    y = np.round(sim.y / step) * step
    run_dataset(_jig_dataset(tmp_path / "ds", y, sim), tmp_path / "out")
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet").filter(pl.col("recommended"))
    u = intrinsic["std_uncertainty"].to_numpy()
    fitted = u > 0  # the orthogonal model fixes the angles at 90 degrees
    z = (intrinsic["value"].to_numpy() - sim.truth)[fitted] / u[fitted]
    assert np.abs(z).max() < 3, z
    diagnosis = tmp_path / "out" / "diagnosis.parquet"
    assert not diagnosis.exists() or not pl.read_parquet(diagnosis)["detected"].any()


def test_output_step_found_from_the_levels():
    rng = np.random.default_rng(3)
    counts = np.round(rng.normal(0, 40, (5000, 3)))
    np.testing.assert_allclose(output_step(counts * 0.000598), 0.000598, rtol=1e-9)  # counts times a scale, as floats
    np.testing.assert_array_equal(output_step(np.round(counts / 100) * 100), 100.0)
    np.testing.assert_array_equal(output_step(rng.normal(0, 1, (5000, 3))), 0.0)   # continuous: no step
    np.testing.assert_array_equal(output_step(np.full((10, 3), 7.0)), 1.0)            # one integer level
    np.testing.assert_array_equal(output_step(np.full((10, 3), 0.25)), 0.0)           # one level, step unknown
    levels = np.array([-16200.0, -800.0, -400.0, 500.0, 900.0, 16300.0])  # six faces at a step of 100: no gap of 100
    assert output_step(levels[:, None])[0] == 100.0 and output_step(levels[:, None] * 0.01)[0] == pytest.approx(1.0)


def test_a_pose_of_identical_samples_is_uncertain_by_the_step():
    """Hand-derived: 50 identical samples at a step of 100 and no noise
    before rounding: the mean's variance is 100^2 / 12 (uniform over the
    step), not (100^2 / 12) / 50; well-dithered samples (noise of a few
    steps) add nothing measurable."""
    y = np.vstack([np.full((50, 3), 300.0), np.full((50, 3), 400.0), np.full((50, 3), -500.0)])
    _, _, cov = group_statistics(y, np.repeat([0, 1, 2], 50), 3)
    np.testing.assert_allclose(np.einsum("kii->ki", cov), 100.0**2 / 12)
    assert mean_rounding_variance(np.array(1.0), np.array(9.0)) < 1e-100


def test_a_dead_channel_without_references_is_named_not_the_pose_geometry(tmp_path):
    """Hand-placed poses without references, channel w all zero: "gravity
    directions lie near one circle" before (the geometry blamed)."""
    from posesim import samples_frame

    sim = hand_placed(4, n_poses=12, samples=300, move_samples=100)
    path = tmp_path / "ds"
    path.mkdir()
    samples_frame(sim).with_columns(w=pl.lit(0.0)).write_csv(path / "session.csv")
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n')
    with pytest.raises(UndeterminedError, match=r"channel w reads 0 in every one of the \d+ poses \(dead"):
        run_dataset(path, tmp_path / "out")


def test_a_reference_of_another_position_is_named(jig, tmp_path):
    """Two positions' jig references swapped: fitted before (the 12
    parameters bent to them, the misfit published as excess scatter); now
    refused naming a swapped position and the angle between its outputs'
    direction and its reference."""
    class Swapped:
        directions = jig.directions.copy()
        pose, t_ns = jig.pose, jig.t_ns

    Swapped.directions[[2, 5]] = Swapped.directions[[5, 2]]
    with pytest.raises(UndeterminedError, match=r"position [36]: its outputs point \d+ degrees from its reference .* a label "
                                                r"or jig reference of another position"):
        run_dataset(_jig_dataset(tmp_path / "ds", jig.y, Swapped), tmp_path / "out")
