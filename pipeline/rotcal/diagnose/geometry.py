"""The samples the diagnosis models (``Observations``), what the table did
for its model (Geist 2017 Eq. 5 with the angle, sampling and force effects
of docs/effects.md, through ``rotcal.model.physics``), and what the model's
evaluations keep between them: the geometries and shared column factors of
the null model's motion and of the last other one, and
the designs' buffers (``Observations.reuse``)."""

from __future__ import annotations

import pickle
import sys
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from rotcal.model.effects import AngleEffect, ForceEffect, SamplingEffect
from rotcal.model.physics import (
    Effects,
    Motion,
    gravity_direction,
    gravity_direction_derivative,
    specific_force,
    true_angle,
    uniform_angle,
)

# Relative to a channel's largest output: far above float64 rounding of the
# model (~1e-15), far below any sensor's noise or quantization (~1e-5).
NUMERICAL_FLOOR = 1e-9
# a time step beyond this many of its segment's median one is a gap between runs (``Observations.run``)
GAP_STEPS = 1.5
# ``motion_reuse``'s key of the null model's motion (no angle, sampling or force effect on)
_NO_MOTION_EFFECT = pickle.dumps([])


@dataclass(frozen=True, eq=False)
class Whitening:
    """Each sample's transform of its residual and Jacobian row,

        x*_i = scale_i (x_i - phi_i x_i-1) / sqrt(1 - phi_i^2),

    per channel (n, 3): ``phi`` a first-order autoregression's coefficient
    (0 at each run's first sample, ``Observations.run``), ``scale`` the pooled noise over its
    group's (``noise.whitening``)."""

    scale: np.ndarray
    phi: np.ndarray

    def rows(self, rows: np.ndarray, r: int) -> tuple[np.ndarray, np.ndarray]:
        """(scale, phi) of channel r's used ``rows`` (ascending), phi 0 where
        the row before is not the sample before."""
        follows = np.r_[False, np.diff(rows) == 1]
        return self.scale[rows, r], np.where(follows, self.phi[rows, r], 0.0)


def filtered(x: np.ndarray, scale: np.ndarray, phi: np.ndarray, axis: int = 0) -> np.ndarray:
    """``Whitening``'s transform of ``x`` along ``axis`` (a new array);
    ``scale`` and ``phi`` broadcast against ``x``."""
    before = np.zeros_like(x)
    inner = [slice(None)] * x.ndim
    inner[axis] = slice(1, None)
    outer = list(inner)
    outer[axis] = slice(None, -1)
    before[tuple(inner)] = x[tuple(outer)]
    return (x - phi * before) * (scale / np.sqrt(1 - phi**2))


@dataclass(frozen=True, eq=False)
class Observations:
    """The samples of a dataset's fitted table segments, as arrays."""

    motion: Motion
    y: np.ndarray           # (n, 3) raw outputs
    rate_idx: np.ndarray    # (n,) index into ``rates``
    rates: np.ndarray       # (m,) rates in Hz, 0 for static
    segment: np.ndarray     # (n,) segment ids
    g_local: float
    # the transform of residuals and Jacobian rows that makes the noise white
    # and equal (``noise.whitening``); None where it is so already
    whitening: Whitening | None = None
    # the geometries and column factors of motions evaluated (``geometry.motion_reuse``), design arrays
    reuse: dict = field(default_factory=dict, init=False, repr=False)

    @property
    def n(self) -> int:
        return self.y.shape[0]

    def whitened(self, resid: np.ndarray, use: np.ndarray | None = None) -> np.ndarray:
        """Residuals (n, 3) as the whitened fit sees them (the samples not
        in ``use`` left out of their successors' filter)."""
        if self.whitening is None:
            return resid
        phi = self.whitening.phi if use is None else self.whitening.phi * np.r_[np.zeros((1, 3), bool), use[:-1]]
        return filtered(resid, self.whitening.scale, phi)

    def sample_noise(self, sigma: np.ndarray) -> np.ndarray:
        """Each sample's noise (n, 3), or (3,) where not whitened, from the
        channels' noise ``sigma`` in the whitened fit."""
        return sigma if self.whitening is None else sigma[None, :] / self.whitening.scale

    @cached_property
    def run(self) -> np.ndarray:
        """(n,) an id per run of samples each of which is the sample after
        the one before: a segment, split where its time step exceeds
        ``GAP_STEPS`` of its median one (the motion between a step
        sequence's steps). Correlated noise links a sample to the one before
        it in time, not to the last of the step before."""
        dt = np.diff(self.motion.t_s)
        within = self.segment[1:] == self.segment[:-1]
        ids, inverse = np.unique(self.segment[1:][within], return_inverse=True)
        typical = np.array([np.median(dt[within][inverse == k]) for k in range(ids.size)])
        follows = np.zeros(dt.size, bool)
        follows[within] = dt[within] <= GAP_STEPS * typical[inverse]
        return np.r_[0, np.cumsum(~follows)]

    @cached_property
    def noise_floor(self) -> np.ndarray:
        """Each channel's smallest credible noise, ``NUMERICAL_FLOOR`` of its
        largest output: on noise-free (simulated) data the residuals are
        rounding, and weighting by them would make rounding look like physics."""
        return NUMERICAL_FLOOR * np.abs(self.y).max(axis=0, initial=0.0)


@dataclass(frozen=True, eq=False)
class Geometry:
    """What the table did, seen at one sampling delay: specific force / g,
    gravity's direction, true angle, d(force)/d(theta) per degree, and the
    uniform angle of the rotating samples. Channels without a delay share one."""

    force: np.ndarray     # (3, n), per component
    up: np.ndarray        # (3, n) gravity's direction (pointing up, Geist 2017 Eq. 5), per component
    theta: np.ndarray
    deriv: np.ndarray     # (3, n), per component
    base: np.ndarray
    stretch: np.ndarray   # d theta / d base: 1 + ripple's slope, per sample (1 when static)


def _geometries(obs: Observations, effects: Effects) -> dict[float, Geometry]:
    m, g = obs.motion, obs.g_local
    scale = np.ones(obs.n)   # of d force / d theta (an axis tilt shrinks the rotating part)
    for force_effect, state in effects.active(ForceEffect):
        factor = force_effect.angle_scale(state, m)
        if factor is not None:
            scale = scale * factor
    out = {}
    rot = np.flatnonzero(m.rotating)
    for delay in sorted(set(effects.delays())):
        theta = true_angle(m, effects, delay)
        base = uniform_angle(m, effects, delay)
        stretch = np.ones(obs.n)
        for angle_effect, state in effects.active(AngleEffect):
            slope = angle_effect.angle_slope(state, m, base)
            if slope is not None:
                stretch[rot] += slope
        # per component, (3, n): a rate's projections are then three contiguous products (``states.project``)
        up = gravity_direction(m.axis_idx, theta)   # once: the force and the axis tilt's column read it
        force = np.ascontiguousarray((specific_force(m, effects, g, delay, up) / g).T)
        deriv = np.ascontiguousarray((gravity_direction_derivative(m.axis_idx, theta) * scale[:, None]).T)
        out[delay] = Geometry(force, np.ascontiguousarray(up.T), theta, deriv, base, stretch)
    return out


def motion_reuse(obs: Observations, effects: Effects) -> dict:
    """What depends only on the samples' motion and on the effects that shape
    it (angle, sampling and force effects): the geometries and the factors
    the extension columns share (``model._Factors.cached``). Kept per
    ``Observations`` for the last values of those effects, bit for bit, and
    for none of them on (the null model's motion, which the fits without
    such effects, the refits without a found one and the corrected samples
    come back to): the iterations of such a fit compute them once, not once
    per evaluation. The arrays are read-only, so no caller can change what
    later ones reuse."""
    key = pickle.dumps([(e.name, state) for stage in (AngleEffect, SamplingEffect, ForceEffect)
                        for e, state in effects.active(stage)])
    slots = obs.reuse.setdefault("motions", {})
    if key not in slots:
        geometries = _geometries(obs, effects)
        for geo in geometries.values():
            for array in (geo.force, geo.up, geo.theta, geo.deriv, geo.base, geo.stretch):
                array.flags.writeable = False
        for old in [k for k in slots if k != _NO_MOTION_EFFECT]:
            del slots[old]
        slots[key] = {"geometries": geometries, "factors": {}}
    return slots[key]


def rate_blocks(obs: Observations) -> list[tuple[int, slice]]:
    """The samples of each rate f, (f, a slice) each: ``observations`` sorts
    them by rate (the model's designs and projections rely on it)."""
    blocks = obs.reuse.get("rate_blocks")
    if blocks is None:
        if np.any(np.diff(obs.rate_idx) < 0):
            raise ValueError("the diagnosis's samples must be sorted by rate")
        cuts = np.searchsorted(obs.rate_idx, np.arange(obs.rates.size + 1))
        blocks = obs.reuse["rate_blocks"] = [(f, slice(a, b)) for f, (a, b) in enumerate(zip(cuts[:-1], cuts[1:]))]
    return blocks


@dataclass(frozen=True)
class Run:
    """Consecutive samples of one rate and one table axis (``samples`` a
    slice of the samples they were cut from), and whether any rotates."""

    rate: int
    axis: int
    rotating: bool
    samples: slice


def runs_of(rate_idx: np.ndarray, axis_idx: np.ndarray, rotating: np.ndarray) -> list[Run]:
    """The samples cut where the rate or the axis changes: the default plan
    visits the axes in turn at each rate, so there are a rate's three runs
    (the columns of an effect on one axis are zero on the other two)."""
    cuts = np.flatnonzero((np.diff(rate_idx) != 0) | (np.diff(axis_idx) != 0)) + 1
    bounds = np.r_[0, cuts, rate_idx.size]
    spins = np.logical_or.reduceat(rotating, bounds[:-1]) if rate_idx.size else np.zeros(0, bool)
    return [Run(int(rate_idx[a]), int(axis_idx[a]), bool(spin), slice(int(a), int(b)))
            for a, b, spin in zip(bounds[:-1], bounds[1:], spins)]


def sample_runs(obs: Observations) -> list[Run]:
    """``runs_of`` every sample, kept with the observations."""
    runs = obs.reuse.get("runs")
    if runs is None:
        runs = obs.reuse["runs"] = runs_of(obs.rate_idx, obs.motion.axis_idx, obs.motion.rotating)
    return runs


def design_buffer(obs: Observations, k: int, n_used: int, width: int) -> np.ndarray:
    """A (k, n_used) array for one channel's design columns (``width`` >=
    k: the widest design of the layout), from a pool kept with the
    observations: a buffer no design refers to any longer is reused, so an
    evaluation does not fault in fresh pages (a few milliseconds for the
    three channels' 12 MB each on the default plan)."""
    pool = obs.reuse.setdefault("designs", [])
    for buffer in pool:
        # referred to only by the pool, this loop and getrefcount's argument: no view of it is alive
        if sys.getrefcount(buffer) == 3 and buffer.shape[0] >= k:
            return buffer[:k, :n_used]
    buffer = np.empty((max(k, width), obs.n))
    pool.append(buffer)
    return buffer[:k, :n_used]
