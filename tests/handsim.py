"""A simulated hand-pose session with effects of the catalogue: ``n_poses``
rests of random orientation, each ``rest_s`` long, joined by smooth turns of
``move_s``; the output chain of ``rotcal.model.physics`` (gain, scale and
offset effects, a temperature history drawn by ``thermal``) as the
simulator's; written as ``t, u, v, w`` (and ``temperature_c``) with a
dataset.toml, for ``rotcal run``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.model.conventions import CHANNELS, Dut, Motion
from rotcal.model.effects import effect_named
from rotcal.model.physics import nonlinearity, observe, offset_terms, scale_terms, scaled
from rotcal.simulate import DutSpec, build_effects, draw_dut
from rotcal.simulate.noise import NoiseSpec, draw_channels
from rotcal.simulate.spec import parse_effect

from posesim import G_LOCAL, random_directions


def session_draws(seed: int, n_poses: int) -> tuple[Dut, np.ndarray, np.random.Generator, np.random.Generator,
                                                   np.random.Generator]:
    """A session's DUT and rest directions as ``hand_session`` draws them,
    with the generators it draws the rest from (turns; effects; noise)."""
    dut_rng, pose_rng, effect_rng, noise_rng = (np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(4))
    dut, _ = draw_dut(DutSpec(), dut_rng)
    return dut, random_directions(pose_rng, n_poses), pose_rng, effect_rng, noise_rng


def hand_session(seed: int, effects: tuple[str, ...] = (), n_poses: int = 30, rest_s: float = 4.0,
                 move_s: float = 3.0, dt_s: float = 0.01, jig: bool = False, excess: float = 0.0,
                 noise: NoiseSpec | None = None) -> tuple[pl.DataFrame, dict]:
    """The samples (``t`` in s, u, v, w, and ``temperature_c`` when an
    effect draws a temperature) and the effects' parameters as drawn;
    ``jig``: each sample's gravity direction as the jig's ``gx, gy, gz``
    (no moves then: every sample rests in a known position); ``excess``:
    each rest's mean shifted by a normal error of that standard deviation
    per channel (output units), as an unsteady hand leaves it; ``noise``:
    the DUT's noise drawn over the whole session in place of its white
    noise (``rotcal.simulate.noise``)."""
    dut, d, pose_rng, effect_rng, noise_rng = session_draws(seed, n_poses)
    requested, described = build_effects(tuple(parse_effect(e) for e in effects), effect_rng)
    rest, move = int(round(rest_s / dt_s)), 0 if jig else int(round(move_s / dt_s))
    blocks, shifts = [], []
    shift = pose_rng.normal(0.0, excess, (n_poses, 3)) if excess else np.zeros((n_poses, 3))
    for k in range(n_poses):
        blocks.append(np.repeat(d[k][None], rest, axis=0))
        shifts.append(np.repeat(shift[k][None], rest, axis=0))
        if k + 1 < n_poses:
            frac = np.linspace(0.0, 1.0, move + 2)[1:-1, None]
            turn = (1 - frac) * d[k] + frac * d[k + 1] + np.sin(np.pi * frac) * random_directions(pose_rng, 1)
            blocks.append(turn / np.linalg.norm(turn, axis=1)[:, None])
            shifts.append(np.zeros((move, 3)))
    direction = np.vstack(blocks)
    n = len(direction)
    t_s = np.arange(n) * dt_s
    zeros = np.zeros(n)
    motion = Motion(t_s, zeros.astype(np.int64), np.zeros(n, bool), zeros, zeros, zeros, zeros, 0.0)
    for item in described:   # the last temperature history requested, as the simulator records it
        history = effect_named(item["effect"]).temperature_history(item["parameters"], motion)
        if history is not None:
            motion = replace(motion, temperature_c=history)
    y = G_LOCAL * direction @ dut.responsivity.T
    x1g = np.linalg.norm(dut.responsivity, axis=1) * G_LOCAL
    clean = np.vstack(shifts) + dut.offsets + offset_terms(motion, requested) + scaled(nonlinearity(y, x1g, requested),
                                                                   scale_terms(motion, requested))
    if noise is not None:
        clean = clean + draw_channels(noise, n, 1 / dt_s, noise_rng, 3)
        dut = replace(dut, noise_std=np.zeros(3))
    out = observe(clean, dut, requested, noise_rng)
    frame = pl.DataFrame({"t": t_s, **{c: out[:, r] for r, c in enumerate(CHANNELS)}})
    if jig:
        frame = frame.with_columns(**{name: direction[:, i] for i, name in enumerate(("gx", "gy", "gz"))})
    if motion.temperature_c is not None:
        frame = frame.with_columns(temperature_c=motion.temperature_c)
    return frame, {k: v for item in described for k, v in item["parameters"].items()}


def write_session(path: Path, frame: pl.DataFrame) -> Path:
    """The samples as ``session.csv`` with a dataset.toml (counts, g_local)."""
    path.mkdir(parents=True, exist_ok=True)
    frame.write_csv(path / "session.csv")
    (path / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n'
                                       "g_local_uncertainty = 0.0\n")
    return path
