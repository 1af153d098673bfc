"""Pose means without scatter (one row per pose, as ellipsoid-fit tools such
as Magneto take them): accepted as pose summaries with the means alone or
as a capture with ``[format] pose_means = true``; the scatter is then the
fit's residuals' (n - p degrees of freedom), and the result is the direct
least-squares fit of the same means, written here independently with
scipy."""

from __future__ import annotations

import numpy as np
import polars as pl
import pytest
from scipy import optimize, stats
from sixfaces import six_faces

from posesim import G_LOCAL, hand_placed

TOML = f"[site]\ng_local = {G_LOCAL}\ng_local_uncertainty = 0.0\n"


def _means(seed: int = 11, n: int = 14) -> np.ndarray:
    sim = hand_placed(seed, n_poses=n, excess=3.0)
    return np.array([sim.y[sim.pose == k].mean(axis=0) for k in range(n)])


def _direct_fit(means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """|L^-1 (m_k - O)| = g by unweighted least squares (L lower
    triangular): the offsets and their classical standard uncertainties
    s^2 (J'J)^-1, s^2 = RSS / (n - 9)."""
    rows, cols = np.tril_indices(3)

    def residuals(p: np.ndarray) -> np.ndarray:
        lower = np.zeros((3, 3))
        lower[rows, cols] = p[:6]
        return np.linalg.norm(np.linalg.solve(lower, (means - p[6:]).T), axis=0) - G_LOCAL

    start = np.concatenate([np.diag(np.full(3, np.ptp(means, axis=0).mean() / (2 * G_LOCAL)))[rows, cols], means.mean(axis=0)])
    fit = optimize.least_squares(residuals, start, method="lm", xtol=1e-14, ftol=1e-14, gtol=1e-14)
    s2 = float(fit.fun @ fit.fun) / (len(means) - 9)
    return fit.x[6:], np.sqrt(np.diag(s2 * np.linalg.inv(fit.jac.T @ fit.jac)))[6:]


def _run(cli, directory, frame: pl.DataFrame, out, toml: str = TOML) -> tuple[int, str, pl.DataFrame | None]:
    directory.mkdir(parents=True, exist_ok=True)
    frame.write_csv(directory / "means.csv")
    (directory / "dataset.toml").write_text(toml)
    status, stdout, stderr = cli("run", directory, "--out", out)
    printed = " ".join((stdout + stderr).split())
    return status, printed, pl.read_parquet(out / "intrinsic.parquet") if status == 0 else None


def test_pose_means_are_the_direct_least_squares_fit(cli, tmp_path):
    """14 means of random orientation: the nine parameters' offsets equal the
    direct fit's (1e-6 relative), their u the classical s^2 (J'J)^-1 (1 %),
    U = t(0.975, 5) u; the console says where the scatter came from."""
    means = _means()
    frame = pl.DataFrame({f"{c}_mean": means[:, i] for i, c in enumerate("uvw")})
    status, printed, intrinsic = _run(cli, tmp_path / "summary", frame, tmp_path / "o1")
    assert status == 0 and intrinsic is not None, printed
    assert "14 pose means without scatter" in printed and "taken from the fit's residuals" in printed
    nine = intrinsic.filter(pl.col("model") == "baseline", pl.col("parameter").str.starts_with("O_"))
    offsets, u = _direct_fit(means)
    np.testing.assert_allclose(nine["value"].to_numpy(), offsets, rtol=1e-6)
    np.testing.assert_allclose(nine["std_uncertainty"].to_numpy(), u, rtol=0.01)
    np.testing.assert_allclose(nine["expanded_uncertainty"].to_numpy() / nine["std_uncertainty"].to_numpy(),
                               stats.t.ppf(0.975, 14 - 9), rtol=1e-6)


def test_a_capture_of_pose_means_gives_the_same_result(cli, tmp_path):
    """The same means as a capture (t, u, v, w) with ``[format] pose_means``."""
    means = _means()
    summary = pl.DataFrame({f"{c}_mean": means[:, i] for i, c in enumerate("uvw")})
    capture = pl.DataFrame({"t": np.arange(14.0), **{c: means[:, i] for i, c in enumerate("uvw")}})
    _, _, first = _run(cli, tmp_path / "summary", summary, tmp_path / "o1")
    status, printed, second = _run(cli, tmp_path / "capture", capture, tmp_path / "o2", TOML + "\n[format]\npose_means = true\n")
    assert status == 0 and first is not None and second is not None, printed
    np.testing.assert_allclose(second["value"].to_numpy(), first["value"].to_numpy(), rtol=1e-12)


@pytest.mark.parametrize("as_summary", [True, False], ids=["summary", "one row per pose"])
def test_six_face_means_without_scatter_say_why(cli, tmp_path, as_summary):
    """Six labelled means without scatter determine the six parameters
    exactly with nothing left for their uncertainty: exit 3, the reason and
    what would serve."""
    session = six_faces(1)
    rests = session.frame.filter(pl.col("face").is_not_null()).group_by("face", maintain_order=True).agg(
        pl.col(c).mean().alias(f"{c}_mean" if as_summary else c) for c in "uvw")
    toml = TOML + '\n[format]\npose_column = "face"\n'
    frame = rests if as_summary else rests.with_columns(t=pl.Series(np.arange(6.0)))
    status, printed, _ = _run(cli, tmp_path / "d", frame, tmp_path / "o", toml)
    assert status == 3, printed
    assert "6 pose means without scatter determine the 6 parameters exactly" in printed and "standard deviation and count" in printed
