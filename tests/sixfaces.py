"""Six faces placed by hand: a DUT drawn within datasheet-like bounds (gains
within 2 %, offsets up to 5 % of full scale, the angles between the axes
within 1 degree of 90, the sensor turned in its case by up to 1 degree),
each face tilted by up to ``tilt_deg`` about a random axis, rests of
``rest_s`` joined by smooth turns; the output chain of
``rotcal.model.physics`` (white noise, rounding, limits)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS, Dut, Effects, intrinsic_from_vectors, observe, rotation_matrix, unit_vectors_from_angles

G_LOCAL = 9.80101
LABELS = ("x_p", "x_a", "y_p", "y_a", "z_p", "z_a")
FACES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
FULL_SCALE = 32768.0  # counts of +-2 g at 16384 counts per g, an MPU-6050's


@dataclass(frozen=True, eq=False)
class SixFaces:
    """Samples (``t`` in s, u, v, w, the face label of each sample, null
    while turning), the truth of the nine parameters, each face's true
    gravity direction and the (up + down) / 2 estimates from the rests."""

    frame: pl.DataFrame
    truth: np.ndarray
    directions: np.ndarray

    def up_down(self) -> tuple[np.ndarray, np.ndarray]:
        """The textbook six-position estimates: per axis, sensitivity
        (up - down) / (2 g) and offset (up + down) / 2 of the rests' means."""
        rest = self.frame.filter(pl.col("face").is_not_null()).group_by("face").agg(pl.col(c).mean() for c in CHANNELS)
        mean = {r["face"]: np.array([r[c] for c in CHANNELS]) for r in rest.iter_rows(named=True)}
        up = np.array([mean[f"{a}_p"][i] for i, a in enumerate("xyz")])
        down = np.array([mean[f"{a}_a"][i] for i, a in enumerate("xyz")])
        return (up - down) / (2 * G_LOCAL), (up + down) / 2


def six_faces(seed: int, tilt_deg: float = 3.0, misalignment_deg: float = 1.0, noise: float = 40.0,
              rest_s: float = 2.0, move_s: float = 1.5, dt_s: float = 0.01, off_label: dict[int, float] | None = None) -> SixFaces:
    """One six-face session; ``off_label``: face index -> its tilt in degrees instead of a random one."""
    rng = np.random.default_rng(seed)
    s = 16384.0 / G_LOCAL * (1 + rng.uniform(-0.02, 0.02, 3))
    unit = unit_vectors_from_angles(*(90 + rng.uniform(-1, 1, 3) * misalignment_deg))
    responsivity = s[:, None] * unit @ rotation_matrix(rng.standard_normal(3), rng.uniform(0, 1))
    offsets = rng.uniform(-0.05, 0.05, 3) * FULL_SCALE
    tilts = rng.uniform(0, tilt_deg, 6)
    for k, tilt in (off_label or {}).items():
        tilts[k] = tilt
    directions = np.array([rotation_matrix(np.cross(f, rng.standard_normal(3)), t) @ f for f, t in zip(FACES, tilts)])
    rest, move = int(round(rest_s / dt_s)), int(round(move_s / dt_s))
    blocks, faces = [], []
    for k, d in enumerate(directions):
        blocks.append(np.repeat(d[None], rest, axis=0))
        faces += [LABELS[k]] * rest
        if k + 1 < len(directions):
            frac = np.linspace(0.0, 1.0, move + 2)[1:-1, None]
            turn = (1 - frac) * d + frac * directions[k + 1] + np.sin(np.pi * frac) * 0.5
            blocks.append(turn / np.linalg.norm(turn, axis=1)[:, None])
            faces += [None] * move
    dut = Dut(responsivity, offsets, np.full(3, noise), full_scale=FULL_SCALE - 1)
    y = observe(offsets + G_LOCAL * np.vstack(blocks) @ responsivity.T, dut, Effects(), rng)
    frame = pl.DataFrame({"t": np.arange(len(y)) * dt_s, **{c: y[:, r] for r, c in enumerate(CHANNELS)},
                          "face": pl.Series(faces, dtype=pl.String)})
    return SixFaces(frame, intrinsic_from_vectors(responsivity, offsets), directions)


def write_six_faces(path: Path, session: SixFaces, labelled: bool, extra_toml: str = "") -> Path:
    """The session as ``faces.csv`` and its dataset.toml: labelled (the
    rests only, ``[format] pose_column = "face"``) or not (every sample,
    the rests found by the stillness detector)."""
    path.mkdir(parents=True, exist_ok=True)
    frame = session.frame.filter(pl.col("face").is_not_null()) if labelled else session.frame.drop("face")
    frame.write_csv(path / "faces.csv")
    fmt = '\n[format]\npose_column = "face"\n' if labelled else ""
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n{extra_toml}\n[site]\ng_local = {G_LOCAL}\n'
                                       f"g_local_uncertainty = 0.0\n{fmt}")
    return path


def pose_tables(session: SixFaces) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The session's rests as the static reduction's pose tables
    (``fit.means.pose_table``): labelled (``source`` label, the
    labels' directions as references) and unlabelled (``source``
    stillness), for the reduction without the run around it."""
    from rotcal.fit.means import pose_table

    rows = session.frame.with_row_index("i").filter(pl.col("face").is_not_null())
    bounds = rows.group_by("face", maintain_order=True).agg(pl.col("i").min().alias("first"), pl.col("i").max().alias("last"))
    t_ns = np.round(session.frame["t"].to_numpy() * 1e9).astype(np.int64)
    poses = pose_table(t_ns, session.frame.select(CHANNELS).to_numpy(), bounds["first"].to_numpy(), bounds["last"].to_numpy() + 1)
    common = {"temperature_c": np.nan}
    labelled = poses.with_columns(label=bounds["face"], source=pl.lit("label"), **common,
                                  **{f"ref_{a}": FACES[:, i] for i, a in enumerate("xyz")})
    unlabelled = poses.with_columns(label=pl.lit(None, pl.String), source=pl.lit("stillness"), **common,
                                    **{f"ref_{a}": np.full(6, np.nan) for a in "xyz"})
    return labelled, unlabelled


def closeness(session: SixFaces, value: np.ndarray, u: np.ndarray) -> dict[str, np.ndarray]:
    """Per seed: whether the offsets and the sensitivities (RMS over the
    three, relative for sensitivities) are at least as close to the truth
    as (up + down) / 2's, and each of the six within 2u of the truth."""
    s_ud, o_ud = session.up_down()
    truth = session.truth
    rms = lambda e: float(np.sqrt(np.mean(e**2)))  # noqa: E731
    return {"offsets": np.array(rms(value[6:] - truth[6:]) <= rms(o_ud - truth[6:])),
            "sensitivities": np.array(rms(value[:3] / truth[:3] - 1) <= rms(s_ud / truth[:3] - 1)),
            "within_2u": np.abs(value - truth)[[0, 1, 2, 6, 7, 8]] <= 2 * u[[0, 1, 2, 6, 7, 8]]}
