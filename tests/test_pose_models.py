"""The nested static models (nine parameters, orthogonal six) and the
choice between them, against simulated hand poses of known truth: the F
test's false-alarm rate, the choice on orthogonal and non-orthogonal DUTs,
honest uncertainties of each model, and the advice that names the missing
pose (scripts/poses_acceptance.py runs the 100-seed figures)."""

import numpy as np
import polars as pl

from rotcal.combine.posemodels import advice, choose_model, determines
from rotcal.fit.means import pose_table
from rotcal.model.results import Failure
from rotcal.run import run_dataset

from posesim import G_LOCAL, HAND_POSES, hand_placed, pose_bounds, samples_frame, tilted

ORTHOGONAL_AXES = (90.0, 90.0, 90.0)
SIX = [0, 1, 2, 6, 7, 8]  # s_u, s_v, s_w, O_u, O_v, O_w


def _choice(sim):
    return choose_model(pose_table(sim.t_ns, sim.y, *pose_bounds(sim)), G_LOCAL, 0.0)


def test_f_test_false_alarm_rate_on_orthogonal_axes():
    """200 sessions of 16 random poses of an orthogonal DUT: the orthogonal
    model is true, so the F test's p-value is uniform; the fraction below
    0.1 lies in the 99.9 % binomial interval around 0.1 (0.031 to 0.169)."""
    p = np.array([_choice(hand_placed(seed, n_poses=16, angles_deg=ORTHOGONAL_AXES)).p_value for seed in range(200)])
    rate = float(np.mean(p < 0.1))
    print(f"p < 0.1 in {rate:.3f}, p < 0.01 in {np.mean(p < 0.01):.3f}")
    assert 0.031 <= rate <= 0.169


def test_hand_poses_without_a_u_v_pose_choose_the_orthogonal_model():
    """Ten hand poses (faces, two between v and w, two between w and u, each
    tilted by about 3 degrees) of an orthogonal DUT, 10 seeds: the six
    parameters are chosen every time, and their sensitivities and offsets
    lie within 3u of the truth; the angles are 90 with zero uncertainty."""
    z = []
    for seed in range(10):
        sim = hand_placed(seed + 1, directions=tilted(HAND_POSES, seed + 1), angles_deg=ORTHOGONAL_AXES)
        choice = _choice(sim)
        assert choice.chosen == "orthogonal", (seed, choice.note)
        result = choice.orthogonal.result
        assert np.all(result.value[3:6] == 90.0) and np.all(result.std_uncertainty[3:6] == 0.0)
        z.append((result.value - sim.truth)[SIX] / result.std_uncertainty[SIX])
    z = np.array(z)
    print(f"orthogonal model: z RMS {np.sqrt(np.mean(z**2)):.3f}, largest {np.abs(z).max():.2f}")
    assert np.abs(z).max() < 3.5 and 0.6 < np.sqrt(np.mean(z**2)) < 1.4


def test_the_full_model_states_phi_uv_honestly():
    """The same ten poses, 30 seeds: the nine-parameter phi_uv rests on the
    tilts alone, so its uncertainty is many times the other angles', and its
    normalised errors have RMS near 1."""
    z, ratio = [], []
    for seed in range(30):
        sim = hand_placed(seed + 1, directions=tilted(HAND_POSES, seed + 1), angles_deg=ORTHOGONAL_AXES)
        full = _choice(sim).full
        if isinstance(full, Failure):
            continue
        u = full.result.std_uncertainty
        z.append((full.result.value[3] - sim.truth[3]) / u[3])
        ratio.append(u[3] / max(u[4], u[5]))
    z = np.array(z)
    print(f"full model phi_uv: {len(z)} of 30 determined, z RMS {np.sqrt(np.mean(z**2)):.3f}, "
          f"u ratio median {np.median(ratio):.1f}")
    assert len(z) >= 27 and 0.7 < np.sqrt(np.mean(z**2)) < 1.35
    assert np.median(ratio) > 5


def test_non_orthogonal_axes_choose_the_nine_parameters():
    """phi_uv = 90.5 degrees, 16 well-placed (random) poses, 10 seeds: the
    F test rejects orthogonal axes every time, and the full model's phi_uv
    is the truth within 3u."""
    for seed in range(10):
        sim = hand_placed(seed, n_poses=16, angles_deg=(90.5, 90.0, 90.0))
        choice = _choice(sim)
        assert choice.chosen == "baseline" and choice.p_value < 1e-6, choice.note
        result = choice.full.result
        assert abs(result.value[3] - 90.5) < 3 * result.std_uncertainty[3]


def test_advice_names_the_pose_no_session_has():
    directions = tilted(HAND_POSES, 3)
    assert advice(directions) == [
        "the poses barely determine phi_uv: none mixes u and v (2 |a_u a_v| / |a|^2 >= 0.5), so it rests on their "
        "small tilts; a pose between +u and +v (gravity about 45 degrees from both) fixes phi_uv"]
    assert determines(HAND_POSES)[6:] == ["phi_vw", "phi_vw", "phi_wu", "phi_wu"] and determines(HAND_POSES)[:6] == [""] * 6
    assert determines(np.array([[1.0, 1.0, 1.0]])) == ["phi_uv phi_vw phi_wu"]


def test_hand_session_end_to_end(tmp_path):
    """The ten hand poses written as one CSV with turns between them: the
    still intervals are found, the orthogonal model is chosen (note), both
    models' rows are written, the warning names the missing pose and the
    pose table says which angle each pose determines."""
    sim = hand_placed(6, samples=300, move_samples=150, directions=tilted(HAND_POSES, 6), angles_deg=ORTHOGONAL_AXES)
    data = tmp_path / "data"
    data.mkdir()
    samples_frame(sim).write_csv(data / "session.csv")
    (data / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n')
    outcome = run_dataset(data, tmp_path / "out")
    assert any(n.startswith("static model: orthogonal: the F test") for n in outcome.notes), outcome.notes
    assert any("a pose between +u and +v" in w for w in outcome.warnings)
    intrinsic = pl.read_parquet(tmp_path / "out" / "intrinsic.parquet")
    assert intrinsic["model"].to_list() == ["baseline"] * 9 + ["orthogonal"] * 9
    poses = pl.read_parquet(tmp_path / "out" / "poses.parquet")
    assert poses.height == 10 and poses["determines"].to_list() == ["", "", "", "", "", "", "phi_vw", "phi_vw", "phi_wu", "phi_wu"]
