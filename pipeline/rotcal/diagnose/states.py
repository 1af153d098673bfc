"""Each channel's model quantities at one parameter vector, per sample: the
offset-free linear output y = R_f,r . a / g of the sample's rate f (the
papers' model, Geist 2017 Eq. 5 through ``geometry``), the gain effects'
factors and chain factor (docs/effects.md, stage 4), and what the extension
columns read besides (``rotcal.model.effects.base.Channel``).

The samples are sorted by rate (``geometry.rate_blocks``), so a rate's
responsivity is three numbers over a block of samples: the projections are
scalar products of the geometry's components, not a gather of a (n, 3, 3)
responsivity per sample; what only some columns read (the responsivity row
per sample, d output / d theta) is computed when first read.
"""

from __future__ import annotations

from functools import cached_property

import numpy as np

from rotcal.diagnose.geometry import Geometry, Observations, motion_reuse, rate_blocks
from rotcal.model.effects import GainEffect
from rotcal.model.physics import Effects, scale_terms, scaled


def project(rows: np.ndarray, vectors: np.ndarray, runs: list[tuple[int, slice]], out: np.ndarray | None = None) -> np.ndarray:
    """rows[f] . vectors per sample of each run (f, samples) of rate f:
    ``rows`` (m, 3) one channel's responsivity row per rate, ``vectors``
    (3, n) per component; ``out`` is left as it is off the runs. The three
    products are summed as numpy's einsum sums them, (0 + 2) + 1, so the
    values are those the per-sample einsum gave, bit for bit."""
    out = np.empty(vectors.shape[1]) if out is None else out
    for f, at in runs:
        row, o, v = rows[f], out[at], vectors[:, at]
        np.multiply(v[0], row[0], out=o)
        o += v[2] * row[2]
        o += v[1] * row[1]
    return out


def _new(out: np.ndarray | None, n: int, runs: list[tuple[int, slice]] | None) -> np.ndarray:
    """``out``, or a new array: zero where ``runs`` (if given) leave it."""
    if out is not None:
        return out
    return np.empty(n) if runs is None else np.zeros(n)


class ChannelState:
    """One channel's model quantities at the current estimate (per sample);
    the ``rotcal.model.effects.base.Channel`` the effects' columns read."""

    def __init__(self, r: int, geo: Geometry, y: np.ndarray, x1g: np.ndarray, u: np.ndarray, slope: np.ndarray,
                 gained: np.ndarray, unit_slope: bool, R_rates: np.ndarray, obs: Observations):
        self.r, self.geo = r, geo
        self.y = y              # offset-free linear output
        self.x1g = x1g          # |R_row|: the output swing for 1 g
        self.u = u              # y / x1g
        self.slope = slope      # d output / d y (the gain effects' chain factor, times the scale effects')
        self.gained = gained    # y times the gain effects' factors (before the scale effects)
        self.unit_slope = unit_slope   # ``slope`` is 1 everywhere (no gain or scale effect)
        self._R_rates, self._obs = R_rates, obs

    def responsivity_times(self, j: int, values: np.ndarray, out: np.ndarray | None = None,
                           runs: list[tuple[int, slice]] | None = None) -> np.ndarray:
        """The responsivity row's component j times ``values`` per sample: one
        number per rate block, so no (n, 3) row per sample is gathered (the
        products are those of the gathered row, bit for bit); on ``runs``
        (rate, samples) alone if given (``out`` left as it is off them)."""
        out = _new(out, values.size, runs)
        rows = self._R_rates[:, self.r]
        for f, at in rate_blocks(self._obs) if runs is None else runs:
            np.multiply(values[at], rows[f, j], out=out[at])
        return out

    def responsivity_dot(self, vectors: np.ndarray, out: np.ndarray | None = None,
                         runs: list[tuple[int, slice]] | None = None) -> np.ndarray:
        """R_row . vectors per sample, ``vectors`` (3, n) per component (on
        ``runs`` alone if given, as ``responsivity_times``)."""
        out = _new(out, vectors.shape[1], runs)
        return project(self._R_rates[:, self.r], vectors, rate_blocks(self._obs) if runs is None else runs, out)

    @cached_property
    def d_theta(self) -> np.ndarray:
        """d output / d theta, per degree."""
        y_theta = project(self._R_rates[:, self.r], self.geo.deriv, rate_blocks(self._obs))
        return y_theta if self.unit_slope else self.slope * y_theta

    @property
    def theta(self) -> np.ndarray:
        return self.geo.theta

    @property
    def up(self) -> np.ndarray:
        return self.geo.up

    @property
    def base(self) -> np.ndarray:
        return self.geo.base

    @property
    def stretch(self) -> np.ndarray:
        return self.geo.stretch


def channel_states(obs: Observations, R_rates: np.ndarray, effects: Effects) -> list[ChannelState]:
    """The three channels' states for the responsivities ``R_rates`` (m, 3, 3)."""
    geometries = motion_reuse(obs, effects)["geometries"]
    blocks = rate_blocks(obs)
    x1g = np.sqrt(np.einsum("fij,fij->fi", R_rates, R_rates))[obs.rate_idx].T  # |R_row| is the rate's
    gains = [(e, np.asarray(k)) for e, k in effects.active(GainEffect)]
    delays = effects.delays()
    scale = scale_terms(obs.motion, effects)
    # channels without a delay share one geometry
    states = []
    for r in range(3):
        geo = geometries[delays[r]]
        y = project(R_rates[:, r], geo.force, blocks)
        u = y / x1g[r]
        # d/dy of y f_1(u) f_2(u) ...: the chain factor of every input, one factor at a time
        slope, product = np.ones(obs.n), np.ones(obs.n)
        for effect, k in gains:
            slope = effect.chain(k[r], slope, product, u)
            product = product * effect.gain(k[r], u)
        slope = scaled(slope, None if scale is None else scale[:, r])
        states.append(ChannelState(r, geo, y, x1g[r], u, slope, y * product if gains else y, not gains and scale is None,
                                   R_rates, obs))
    return states
