"""Issue 13, deliverable 2: pose summaries (one row per pose: label or
reference, and per channel mean, standard deviation and count) are reduced
exactly like the samples they summarise.

Truth: a six-pose labelled session simulated by ``posesim`` and its own
summaries (numpy's mean, std with ddof = 1, count), run both ways."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from posesim import hand_placed  # noqa: E402

LABELS = ["x_p", "x_a", "y_p", "y_a", "z_p", "z_a"]
DIRECTIONS = np.repeat(np.eye(3), 2, axis=0) * np.tile([1.0, -1.0], 3)[:, None]
TOML = '[site]\ng_local = 9.80101\ng_local_uncertainty = 3e-5\n\n[format]\npose_column = "part"\n'


def session(seed: int, directions: np.ndarray = DIRECTIONS):
    return hand_placed(seed, directions=directions, samples=250)


def summary_rows(sim, per_channel_counts: bool = False, correlations: bool = False) -> pl.DataFrame:
    """Each pose's mean, sample standard deviation and count, per channel
    (and the channels' sample correlations)."""
    rows = []
    for k in range(len(sim.directions)):
        y = sim.y[sim.pose == k]
        counts = {f"{c}_n": len(y) for c in "uvw"} if per_channel_counts else {"n": len(y)}
        r = np.corrcoef(y.T)
        corr = {"corr_uv": r[0, 1], "corr_vw": r[1, 2], "corr_wu": r[2, 0]} if correlations else {}
        rows.append({**{f"{c}_mean": y[:, i].mean() for i, c in enumerate("uvw")},
                     **{f"{c}_std": y[:, i].std(ddof=1) for i, c in enumerate("uvw")}, **counts, **corr})
    return pl.DataFrame(rows)


def run(cli, directory: Path, frame: pl.DataFrame, out: Path, toml: str = TOML) -> pl.DataFrame:
    directory.mkdir()
    frame.write_csv(directory / "data.csv")  # floats written to round-trip exactly
    (directory / "dataset.toml").write_text(toml)
    status, _, err = cli("run", directory, "--out", out)
    assert status == 0, err
    return pl.read_parquet(out / "intrinsic.parquet").sort("parameter")


@pytest.mark.parametrize("seed", [1, 2])
def test_six_pose_session_and_its_summaries_give_the_same_parameters(cli, tmp_path, seed):
    sim = session(seed)
    samples = pl.DataFrame({"t": sim.t_ns / 1e9, **{c: sim.y[:, i] for i, c in enumerate("uvw")},
                            "part": np.array(LABELS)[sim.pose]})
    from_samples = run(cli, tmp_path / "samples", samples, tmp_path / "o1")
    plain = summary_rows(sim, per_channel_counts=seed == 2).with_columns(part=pl.Series(LABELS))
    from_summaries = run(cli, tmp_path / "summaries", plain, tmp_path / "o2")
    correlated = summary_rows(sim, correlations=True).with_columns(part=pl.Series(LABELS))
    from_correlated = run(cli, tmp_path / "correlated", correlated, tmp_path / "o3")
    assert from_samples["parameter"].to_list() == from_summaries["parameter"].to_list()
    for summarised in (from_summaries, from_correlated):
        np.testing.assert_allclose(summarised["value"], from_samples["value"], rtol=1e-9, atol=0)
    # with the channels' correlations every uncertainty is the samples' too
    np.testing.assert_allclose(from_correlated["std_uncertainty"], from_samples["std_uncertainty"], rtol=1e-9)
    # without them nearly: |a| of a face mixes the channels slightly, whose covariance (independent
    # noise: a sample correlation of ~1/sqrt(n)) is then missed
    np.testing.assert_allclose(from_summaries["std_uncertainty"], from_samples["std_uncertainty"], rtol=0.01)
    # and both near the simulated truth (independent of either path)
    truth = dict(zip(["s_u", "s_v", "s_w", "phi_uv", "phi_vw", "phi_wu", "O_u", "O_v", "O_w"], sim.truth))
    # six faces: the orthogonal model (its angles fixed), sensitivities and offsets against the truth
    six = from_summaries.filter(pl.col("model") == "orthogonal", ~pl.col("parameter").str.starts_with("phi"))
    for name, value, u in six.select("parameter", "value", "std_uncertainty").iter_rows():
        assert abs(value - truth[name]) < 5 * u, (name, value, truth[name], u)


def test_jig_reference_summaries_match_their_samples(cli, tmp_path):
    """Summaries placed by their references gx, gy, gz in g (a tilted jig)."""
    tilt = np.radians(30.0)
    turn = np.array([[np.cos(tilt), 0, np.sin(tilt)], [0, 1, 0], [-np.sin(tilt), 0, np.cos(tilt)]])
    directions = np.vstack([DIRECTIONS, DIRECTIONS @ turn.T])
    sim = session(3, directions)
    refs = {f"g{a}": sim.directions[:, i] for i, a in enumerate("xyz")}
    samples = pl.DataFrame({"t": sim.t_ns / 1e9, **{c: sim.y[:, i] for i, c in enumerate("uvw")},
                            **{k: v[sim.pose] for k, v in refs.items()}})
    toml = TOML.replace('pose_column = "part"\n', "")
    from_samples = run(cli, tmp_path / "samples", samples, tmp_path / "o1", toml)
    from_summaries = run(cli, tmp_path / "summaries", summary_rows(sim).with_columns(**refs), tmp_path / "o2", toml)
    np.testing.assert_allclose(from_summaries["value"], from_samples["value"], rtol=1e-9, atol=0)
    poses = pl.read_parquet(tmp_path / "o2" / "poses.parquet")
    assert poses["source"].unique().to_list() == ["jig"] and poses["n_samples"].to_list() == [250] * 12


def test_one_row_per_pose_as_samples_is_one_line(cli, tmp_path):
    """A file of six pose means in the sample columns used to end in a divide
    by zero and LinAlgError; it is refused with one line naming the way out."""
    sim = session(4)
    means = summary_rows(sim)
    frame = pl.DataFrame({"t": np.arange(6) * 1.0, "u": means["u_mean"], "v": means["v_mean"], "w": means["w_mean"],
                          "part": LABELS})
    directory = tmp_path / "means"
    directory.mkdir()
    frame.write_csv(directory / "means.csv")
    (directory / "dataset.toml").write_text(TOML)
    status, _, err = cli("run", directory, "--out", tmp_path / "o")
    lines = err.strip().splitlines()
    assert status == 3 and len(lines) == 1 and "Traceback" not in err, err
    # one row per pose: six pose means without scatter, which determine the six parameters with no residual left
    assert "6 pose means without scatter determine the 6 parameters exactly" in lines[0] and "pose summaries" in lines[0]


@pytest.mark.parametrize("change, needle", [
    (lambda f: f.with_columns(n=pl.lit(1)), "column 'u_n', row 1: 1 is not a sample count of 2 or more"),
    (lambda f: f.with_columns(v_std=pl.lit(0.0)), "column 'v_std', row 1: a standard deviation of 0"),
    (lambda f: f.drop("w_std"), "pose summaries need the columns 'w_std'"),
    (lambda f: f.with_columns(part=pl.Series(["tilted", *LABELS[1:]])), "row 1: neither a pose label"),
    (lambda f: f.with_columns(u_mean=pl.lit(None, pl.Float64)), "column 'u_mean', row 1 is empty"),
    (lambda f: f.with_columns(corr_uv=pl.lit(1.5)), "column 'corr_uv', row 1: 1.5 is not a correlation"),
], ids=["one sample", "no scatter", "missing column", "no pose", "empty mean", "correlation beyond 1"])
def test_bad_summaries_are_one_line(cli, tmp_path, change, needle):
    sim = session(5)
    directory = tmp_path / "bad"
    directory.mkdir()
    change(summary_rows(sim).with_columns(part=pl.Series(LABELS))).write_csv(directory / "poses.csv")
    (directory / "dataset.toml").write_text(TOML)
    status, _, err = cli("run", directory, "--out", tmp_path / "o")
    lines = err.strip().splitlines()
    assert status == 2 and len(lines) == 1 and "poses.csv" in lines[0], err
    assert needle in lines[0], lines[0]


def test_summaries_and_samples_in_one_dataset_are_refused(cli, tmp_path):
    sim = session(6)
    directory = tmp_path / "mixed"
    directory.mkdir()
    summary_rows(sim).with_columns(part=pl.Series(LABELS)).write_csv(directory / "a_poses.csv")
    pl.DataFrame({"t": sim.t_ns / 1e9, **{c: sim.y[:, i] for i, c in enumerate("uvw")}}).write_csv(directory / "b.csv")
    (directory / "dataset.toml").write_text(TOML)
    status, _, err = cli("run", directory, "--out", tmp_path / "o")
    assert status == 2 and "'a_poses.csv' holds pose summaries and 'b.csv' samples" in err, err
