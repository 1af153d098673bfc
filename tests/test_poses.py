"""Calibration against known reference accelerations (labelled poses, jig
positions): simulated truth, refusals, and imucal's Ferraris result on its
own annotated session."""

import json

import numpy as np
import pytest

from rotcal.combine.multiposition import pose_arrays
from rotcal.combine.poses import LABEL_REFERENCE, correct_poses, labelled_poses, reference_fit
from rotcal.fit.means import pose_table
from rotcal.ingest.dataset import load_dataset
from rotcal.model.results import Failure
from rotcal.segment.labelled import segment_by_labels

from posesim import G_LOCAL, hand_placed, pose_bounds, random_directions
from testdata import REAL, REPO

FACES = np.array([LABEL_REFERENCE[k] for k in ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")])


def _jig_poses(sim):
    poses = pose_table(sim.t_ns, sim.y, *pose_bounds(sim))
    return poses.with_columns(**{f"ref_{s}": sim.directions[:, i] for i, s in enumerate("xyz")})


def test_noise_free_positions_give_the_truth():
    sim = hand_placed(1, samples=10, noise=0.0, integer=False, directions=np.vstack([FACES, random_directions(np.random.default_rng(1), 3)]))
    fit = reference_fit(_jig_poses(sim), G_LOCAL, 0.0)
    np.testing.assert_allclose(fit.result.value, sim.truth, rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(fit.result.responsivity, sim.responsivity, rtol=1e-10)
    assert fit.dof == 3 * (9 - 4)
    np.testing.assert_allclose(correct_poses(fit.result, *pose_arrays(_jig_poses(sim))).magnitude, G_LOCAL, rtol=1e-12)


def test_uncertainty_covers_over_repeated_sessions():
    """80 sessions of the six faces plus two diagonal jig positions, 8
    counts of noise: the noise alone explains the residuals, and the
    normalised errors of all nine parameters have RMS near 1."""
    diag = np.array([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0]]) / np.sqrt(3)
    z = []
    for seed in range(300, 380):
        sim = hand_placed(seed, samples=100, directions=np.vstack([FACES, diag]))
        fit = reference_fit(_jig_poses(sim), G_LOCAL, 0.0)
        z.append((fit.result.value - sim.truth) / fit.result.std_uncertainty)
    rms = np.sqrt(np.mean(np.array(z) ** 2, axis=0))
    print(f"z RMS per parameter {np.round(rms, 3)}")
    assert np.all((rms > 0.75) & (rms < 1.3)), rms


def test_refuses_too_few_or_coplanar_references():
    sim = hand_placed(2, samples=20, directions=FACES)
    few = reference_fit(_jig_poses(sim).head(3), G_LOCAL, 0.0)
    assert isinstance(few, Failure) and "at least 4" in few.reason
    flat = reference_fit(_jig_poses(sim).head(4), G_LOCAL, 0.0)  # x and y faces only: z never excited
    assert isinstance(flat, Failure) and "do not determine the 12 parameters" in flat.reason


# --- imucal's annotated session (../shared/data/real/imucal_session) ---

@pytest.fixture(scope="module")
def imucal():
    ds = load_dataset(REAL / "imucal_session", REPO / "configs" / "imucal_session.toml")
    samples, segments = segment_by_labels(ds.samples, ds.name)
    poses = labelled_poses(samples, segments)
    reference = json.loads((REAL / "imucal_session" / "annotated_session_reference_cal.json").read_text())
    return ds, poses, reference


def _means_by_label(poses):
    m, _ = pose_arrays(poses)
    return dict(zip(poses["label"], m))


@pytest.mark.real
def test_imucal_poses_and_the_gravity_imucal_expects(imucal):
    ds, poses, _ = imucal
    assert ds.meta.g_local == 9.81  # FerrarisCalibration(grav=9.81), imucal/ferraris_calibration.py
    assert sorted(poses["label"]) == ["x_a", "x_p", "y_a", "y_p", "z_a", "z_p"]
    assert dict(zip(poses["label"], poses["n_samples"])) == {"x_a": 1061, "x_p": 1028, "y_a": 848, "y_p": 734, "z_a": 1044, "z_p": 881}
    assert set(poses["source"]) == {"label"}


@pytest.mark.real
def test_forward_fit_reproduces_imucal_scale_and_misalignment(imucal):
    """The 12-parameter forward fit on the six pose means gives K_a R_a
    (counts per m/s^2; imucal's model acc = R_a^-1 K_a^-1 (raw - b_a)) to
    1e-6 relative, with 3 x (6 - 4) = 6 residual degrees of freedom."""
    ds, poses, ref = imucal
    fit = reference_fit(poses, ds.meta.g_local, ds.meta.g_local_uncertainty)
    k_r = np.array(ref["K_a"]) @ np.array(ref["R_a"])
    np.testing.assert_allclose(fit.result.responsivity, k_r, rtol=1e-6)
    np.testing.assert_allclose(fit.result.value[:3], np.diag(ref["K_a"]) * np.linalg.norm(ref["R_a"], axis=1), rtol=1e-6)
    assert fit.dof == 6


@pytest.mark.real
def test_ferraris_offsets_are_each_channels_own_pair_midpoint(imucal):
    """Why rotcal's offsets differ from imucal's b_a. With B the midpoints
    (U_p + U_a) / 2 of the three up/down pairs (column j: pair j, row r:
    channel r; imucal's Eq. 20 B_a), Ferraris takes b_a = diag(B), each
    channel's offset from its own pair only. The least-squares fit of the
    six poses, whose reference columns are orthogonal to the constant,
    takes each channel's mean over all six poses: the row means of B. They
    differ wherever a channel's zero-g readings (the four poses
    perpendicular to it) disagree with its +-1 g midpoint: up and down
    faces that are not exactly antipodal, or even-order nonlinearity."""
    ds, poses, ref = imucal
    means = _means_by_label(poses)
    B = np.column_stack([(means[f"{s}_p"] + means[f"{s}_a"]) / 2 for s in "xyz"])
    np.testing.assert_allclose(np.diag(B), ref["b_a"], rtol=1e-9)
    fit = reference_fit(poses, ds.meta.g_local, ds.meta.g_local_uncertainty)
    offsets = fit.result.value[6:]
    np.testing.assert_allclose(offsets, B.mean(axis=1), rtol=1e-12)
    np.testing.assert_allclose(offsets - np.array(ref["b_a"]), B.mean(axis=1) - np.diag(B), rtol=1e-9)
    # the differences in counts, and the largest disagreement behind them:
    # channel v reads -73.0 counts at zero g in the z poses, -48.3 at its own +-1 g midpoint
    np.testing.assert_allclose(offsets - np.array(ref["b_a"]), [-1.855, -7.655, -2.064], atol=1e-3)
    assert B[1, 2] - B[1, 1] == pytest.approx(-24.76, abs=0.01)
    # the fit sees the disagreement as residuals: per pair, equal for up and down
    np.testing.assert_allclose(fit.residuals[::2], fit.residuals[1::2], atol=1e-9)
    assert np.abs(fit.residuals).max() == pytest.approx(17.10, abs=0.01)


@pytest.mark.real
def test_imucal_calibration_and_rotcal_fit_magnitudes(imucal):
    """|a| per pose: imucal's own calibration gives g within 0.02 % in its
    six poses (Ferraris forces each channel's pair to +-g); rotcal's fit,
    which also honours the zero-g readings, spreads them by its residuals."""
    ds, poses, ref = imucal
    m, cov = pose_arrays(poses)
    k_r = np.array(ref["K_a"]) @ np.array(ref["R_a"])
    imucal_mag = np.linalg.norm(np.linalg.solve(k_r, (m - ref["b_a"]).T), axis=0)
    np.testing.assert_allclose(imucal_mag, 9.81, rtol=2e-4)
    fit = reference_fit(poses, ds.meta.g_local, ds.meta.g_local_uncertainty)
    mag = correct_poses(fit.result, m, cov).magnitude
    by_label = dict(zip(poses["label"], mag / 9.81 - 1))
    assert by_label["y_p"] == pytest.approx(0.00379, abs=5e-5) and by_label["y_a"] == pytest.approx(-0.00378, abs=5e-5)
    assert np.abs(mag / 9.81 - 1).max() < 0.004
