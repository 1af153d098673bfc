"""Simulated hand-placed static poses of random orientation, from the forward
model of ``rotcal.model.physics`` (a DUT drawn as ``simulate`` draws one; noise,
rounding and clipping by ``observe``)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import polars as pl

from rotcal.model.physics import CHANNELS, Effects, intrinsic_from_vectors, observe, rotation_matrix, unit_vectors_from_angles
from rotcal.simulate import DutSpec, draw_dut

G_LOCAL = 9.80101


@dataclass(frozen=True, eq=False)
class HandPlaced:
    """Samples (n, 3), the pose of each sample (-1 while moving), the true
    gravity direction of each pose (in the DUT's table-like frame) and the
    truth of the nine intrinsic parameters."""

    t_ns: np.ndarray
    y: np.ndarray
    pose: np.ndarray
    directions: np.ndarray
    truth: np.ndarray
    responsivity: np.ndarray
    offsets: np.ndarray


def random_directions(rng: np.random.Generator, n: int) -> np.ndarray:
    d = rng.standard_normal((n, 3))
    return d / np.linalg.norm(d, axis=1)[:, None]


def hand_placed(seed: int, n_poses: int = 24, samples: int = 200, noise: float = 8.0, excess: float = 0.0,
                move_samples: int = 0, directions: np.ndarray | None = None, dt_s: float = 0.01,
                integer: bool = True, angles_deg: tuple[float, float, float] | None = None) -> HandPlaced:
    """``n_poses`` static poses of ``samples`` samples each; ``excess`` adds
    a random shift (output units) to each pose's mean, as low-frequency noise
    or an unsteady hand would; ``move_samples`` > 0 puts a smooth turn
    between poses (samples labelled -1). With ``angles_deg`` the DUT has
    those angles (phi_uv, phi_vw, phi_wu) and no mount rotation: the
    directions are then in its intrinsic frame (u along x, v in x-y)."""
    rng = np.random.default_rng(seed)
    dut, _ = draw_dut(DutSpec(noise_std=noise, integer_output=integer), rng)
    if angles_deg is not None:
        s = np.linalg.norm(dut.responsivity, axis=1)
        dut = replace(dut, responsivity=unit_vectors_from_angles(*angles_deg) * s[:, None])
    d = random_directions(rng, n_poses) if directions is None else directions
    n_poses = len(d)
    shift = rng.normal(0.0, excess, (n_poses, 3)) if excess else np.zeros((n_poses, 3))
    blocks, labels = [], []
    for k in range(n_poses):
        blocks.append(np.repeat(d[k][None], samples, axis=0))
        labels.append(np.full(samples, k))
        if move_samples and k + 1 < n_poses:
            f = np.linspace(0.0, 1.0, move_samples + 2)[1:-1, None]
            turn = (1 - f) * d[k] + f * d[k + 1] + np.sin(np.pi * f) * random_directions(rng, 1)
            blocks.append(turn / np.linalg.norm(turn, axis=1)[:, None])
            labels.append(np.full(move_samples, -1))
    direction = np.vstack(blocks)
    pose = np.concatenate(labels)
    clean = dut.offsets[None] + G_LOCAL * direction @ dut.responsivity.T
    clean[pose >= 0] += shift[pose[pose >= 0]]
    y = observe(clean, dut, Effects(), rng)
    t_ns = np.arange(len(y), dtype=np.int64) * int(round(dt_s * 1e9))
    truth = intrinsic_from_vectors(dut.responsivity, dut.offsets)
    return HandPlaced(t_ns, y, pose, d, truth, dut.responsivity, dut.offsets)


def samples_frame(sim: HandPlaced) -> pl.DataFrame:
    return pl.DataFrame({"t": sim.t_ns / 1e9, **{c: sim.y[:, r] for r, c in enumerate(CHANNELS)}})


def pose_bounds(sim: HandPlaced) -> tuple[np.ndarray, np.ndarray]:
    """First sample and one past the last sample of each pose."""
    edges = np.array([np.flatnonzero(sim.pose == k)[[0, -1]] for k in range(len(sim.directions))])
    return edges[:, 0], edges[:, 1] + 1


# ten hand poses in the intrinsic frame: the six faces, two between v and w, two between w and u, none between u and v
_R = np.sqrt(0.5)
HAND_POSES = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1],
                       [0, _R, _R], [0, -_R, _R], [_R, 0, _R], [-_R, 0, _R]], float)


def tilted(directions: np.ndarray, seed: int, tilt_deg: float = 3.0) -> np.ndarray:
    """Each direction turned about a random axis by a normal angle of
    ``tilt_deg`` standard deviation: a hand never places a pose exactly."""
    rng = np.random.default_rng(10_000 + seed)
    return np.array([rotation_matrix(rng.standard_normal(3), rng.normal(0.0, tilt_deg)) @ d for d in directions])


def reference_pose_table(sim: HandPlaced, reference: np.ndarray) -> pl.DataFrame:
    """The pose table of ``sim`` with each pose's known reference
    (``ref_x, ref_y, ref_z``; the nominal direction a label or jig states)."""
    from rotcal.fit.means import pose_table

    poses = pose_table(sim.t_ns, sim.y, *pose_bounds(sim))
    return poses.with_columns(**{name: reference[:, i] for i, name in enumerate(("ref_x", "ref_y", "ref_z"))})
