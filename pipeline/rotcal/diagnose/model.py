"""The whole-dataset model the diagnosis fits, and its Jacobian.

The null model is the papers' model, simulated for every sample: per rate f
a responsivity matrix R_f (rows u, v, w, output unit per g) and offsets O_f,

    R_r(t) = O_f,r + R_f,r . a(theta(t)) / g,

with a from docs/conventions.md. Extensions (``candidates``) add the effects
of docs/effects.md through the same forward model the simulator uses
(``physics.specific_force``, ``nonlinearity``, ``offset_terms``); each
effect of the catalogue supplies its own Jacobian column. Generic
structures (an offset step). Every parameter, enabled or not, has an
analytic Jacobian column at the current estimate; one weighted Gram matrix
then gives the Gauss-Newton step of any subset of parameters, and so the
fit of any nested model and the score (likelihood-ratio) statistic of any
extension, without refitting from scratch.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from rotcal.diagnose.candidates import STEP, effects_from
from rotcal.diagnose.design import GROUPS, ChannelDesign, Evaluation, normal_equations, support_group
from rotcal.diagnose.geometry import Observations, design_buffer, filtered, motion_reuse, runs_of, sample_runs
from rotcal.diagnose.states import ChannelState, channel_states
from rotcal.model.effects import GainEffect, ScaleEffect, catalogue, effect_named
from rotcal.model.effects.base import EVERYWHERE, Candidate, Channel, Support
from rotcal.model.physics import (
    Effects,
    nonlinearity,
    offset_terms,
    scale_terms,
    scaled,
)


class Layout:
    """Parameter order: offsets O (rate, channel), responsivities R (rate,
    channel, component), then every candidate's parameters; each extension
    parameter's ``support_group``."""

    def __init__(self, n_rates: int, candidates: tuple[Candidate, ...]):
        names = [f"O.{f}.{r}" for f in range(n_rates) for r in range(3)]
        names += [f"R.{f}.{r}.{c}" for f in range(n_rates) for r in range(3) for c in range(3)]
        channels: list[tuple[int, ...]] = [(r,) for f in range(n_rates) for r in range(3)]
        channels += [(r,) for f in range(n_rates) for r in range(3) for c in range(3)]
        self.n_base = len(names)
        self.candidates = candidates
        groups = [0] * self.n_base
        for cand in candidates:
            names += cand.names
            channels += cand.channels
            groups += [support_group(EVERYWHERE if cand == STEP else effect_named(cand.effect).support(cand))] * len(cand.names)
        self.group = np.array(groups)
        self.names = tuple(names)
        self.index = {n: i for i, n in enumerate(names)}
        self.n_rates = n_rates
        self.per_channel = [np.array([i for i, ch in enumerate(channels) if r in ch]) for r in range(3)]

    def params(self, cand: Candidate) -> np.ndarray:
        return np.array([self.index[n] for n in cand.names])

    def mask(self, idx: np.ndarray) -> np.ndarray:
        """Parameter numbers ``idx`` as a mask over every parameter (``np.isin`` took 0.1 ms a call)."""
        chosen = np.zeros(len(self.names), bool)
        chosen[idx] = True
        return chosen

    def offsets(self, beta: np.ndarray) -> np.ndarray:
        return beta[: 3 * self.n_rates].reshape(self.n_rates, 3)

    def responsivity(self, beta: np.ndarray) -> np.ndarray:
        return beta[3 * self.n_rates : self.n_base].reshape(self.n_rates, 3, 3)

    def values(self, beta: np.ndarray, active: tuple[Candidate, ...]) -> dict[str, float]:
        return {n: float(beta[self.index[n]]) for c in active for n in c.names}


@dataclass(frozen=True)
class Structure:
    """Generic structures in the model: the offset step's time (or None)."""

    step_t_s: float | None = None


def predict(obs: Observations, beta: np.ndarray, layout: Layout, active: tuple[Candidate, ...],
            clip: tuple[float | None, float | None], structure: Structure) -> np.ndarray:
    """The model's outputs (n, 3): the simulation of every sample."""
    effects = effects_from(layout.values(beta, active), clip)
    return _outputs(obs, beta, layout, active, effects, channel_states(obs, layout.responsivity(beta), effects), structure)


def _outputs(obs, beta, layout, active, effects, states, structure) -> np.ndarray:
    y = np.column_stack([st.y for st in states])
    if effects.active(GainEffect):   # (without, the gain effects' product is y itself)
        y = nonlinearity(y, np.column_stack([st.x1g for st in states]), effects)
    gained = scaled(y, scale_terms(obs.motion, effects))
    out = layout.offsets(beta)[obs.rate_idx] + offset_terms(obs.motion, effects) + gained
    if structure.step_t_s is not None and STEP in active:
        after = (obs.motion.t_s >= structure.step_t_s)[:, None]
        out = out + after * np.array([beta[layout.index[n]] for n in STEP.names])[None, :]
    low, high = effects.limits()
    if np.isfinite(low) or np.isfinite(high):
        out = np.clip(out, low, high)
    return out


class _Factors:
    """What the extension columns use besides their channel (the
    ``rotcal.model.effects.base.ColumnContext``): channel-independent
    factors are computed once and cached with the geometries
    (``geometry.motion_reuse``): a factor may depend on the motion, the geometry
    and the effects that shape them, nothing else."""

    def __init__(self, obs: Observations, effects: Effects, structure: Structure):
        self.obs, self.effects, self.structure = obs, effects, structure
        self.motion, self.g_local = obs.motion, obs.g_local
        self.cache: dict = motion_reuse(obs, effects)["factors"]
        self.on_axis = self.cached("on_axis", lambda: [obs.motion.axis_idx == a for a in range(3)])

    def runs(self, support: Support) -> list[tuple[int, slice]]:
        """(rate, samples) of the runs holding ``support``'s samples."""
        return [(run.rate, run.samples) for run in sample_runs(self.obs)
                if support.axis in (None, run.axis) and (run.rotating or not support.rotating)]

    def cached(self, key, make):
        if key not in self.cache:
            value = make()
            for array in value if isinstance(value, list) else [value]:
                array.flags.writeable = False
            self.cache[key] = value
        return self.cache[key]

    def gain_column(self, effect: GainEffect, st: Channel, out: np.ndarray | None = None) -> np.ndarray:
        """d output / d k of a gain effect: y times d f / d k and the other
        gain factors, in the forward model's order (into ``out`` if given)."""
        column = st.y
        for other in catalogue():
            if other is effect:
                column = np.multiply(column, effect.gain_derivative(st.u), out=out)
            elif isinstance(other, GainEffect) and other.name in self.effects.states:
                column = np.multiply(column, other.gain(np.asarray(self.effects.states[other.name])[st.r], st.u), out=out)
        return self._scaled(column, st.r, out=out)

    def _scaled(self, column: np.ndarray, r: int, leave: ScaleEffect | None = None,
                out: np.ndarray | None = None) -> np.ndarray:
        """``column`` times channel r's scale effects' factors (but ``leave``'s)."""
        for other, state in self.effects.active(ScaleEffect):
            if other is not leave:
                column = np.multiply(column, other.scale(state, self.motion)[:, r], out=out)
        return column

    def scale_column(self, effect: ScaleEffect, st: Channel, derivative: np.ndarray,
                     out: np.ndarray | None = None) -> np.ndarray:
        """d output / d p of a scale effect's parameter p: the gained output
        times d (its factor) / d p and the other scale effects' factors."""
        return self._scaled(np.multiply(st.gained, derivative, out=out), st.r, leave=effect, out=out)

    def column(self, name: str, cand: Candidate, st: ChannelState, out: np.ndarray | None = None) -> np.ndarray:
        """The Jacobian column of one extension parameter in channel
        ``st.r``'s equation (``out``: an array it may be written into)."""
        if cand == STEP:
            m = self.motion
            t = self.structure.step_t_s
            return self.cached(("step", t), lambda: (m.t_s >= t).astype(float) if t is not None else np.zeros(self.obs.n))
        return effect_named(cand.effect).column(name, cand, st, self, out)


class Linearisation:
    """The model at one parameter vector: predictions and residuals, and
    the Jacobian's columns built on demand and kept, so that a Gauss-Newton
    iteration builds only the active parameters' columns and the converged
    one adds the rest (``evaluation``) without building any twice."""

    def __init__(self, obs: Observations, beta: np.ndarray, layout: Layout, active: tuple[Candidate, ...],
                 clip: tuple[float | None, float | None], structure: Structure, use: np.ndarray):
        effects = effects_from(layout.values(beta, active), clip)
        self.obs, self.layout, self.use = obs, layout, use
        self.states = channel_states(obs, layout.responsivity(beta), effects)
        self.pred = _outputs(obs, beta, layout, active, effects, self.states, structure)
        self.factors = _Factors(obs, effects, structure)
        self.resid = np.where(use, obs.whitened(obs.y - self.pred, use), 0.0)
        self.by_name = {n: c for c in layout.candidates for n in c.names}
        self.built: dict[tuple[int, int], np.ndarray] = {}

    def _column(self, r: int, i: int, rows: np.ndarray | None, keep: bool, row: np.ndarray,
                runs: list[slice] | None = None) -> None:
        """Channel r's column of parameter i on the used ``rows`` (None:
        every sample) into ``row``, the design's (on ``runs`` of the used
        samples alone, if given). ``keep``: kept for a later evaluation (the
        active parameters'); the others are computed into the design's row
        itself when every sample is used (no copy)."""
        column = self.built.get((r, i))
        if column is None:
            name = self.layout.names[i]
            column = self.factors.column(name, self.by_name[name], self.states[r],
                                         None if keep or rows is not None else row)
            if keep:
                self.built[r, i] = column
        if column is row:
            return
        for at in [slice(None)] if runs is None else runs:
            if rows is None:
                np.copyto(row[at], column[at])
            else:
                np.take(column, rows[at], out=row[at])

    def evaluation(self, params: np.ndarray | None = None) -> Evaluation:
        """The normal equations of the Jacobian's columns of the base
        parameters and the extension parameters ``params`` (None: all);
        the others' rows and columns are zero."""
        obs, layout, use = self.obs, self.layout, self.use
        p, m = len(layout.names), layout.n_rates
        designs, grams, rhss = [], [], []
        width = 4 + max(int((channel >= layout.n_base).sum()) for channel in layout.per_channel)
        chosen = None if params is None else layout.mask(params)
        for st in self.states:
            r = st.r
            rows = np.flatnonzero(use[:, r])
            every = rows.size == obs.n
            ext = layout.per_channel[r][layout.per_channel[r] >= layout.n_base]
            if chosen is not None:
                ext = ext[chosen[ext]]
            ext = ext[np.argsort(layout.group[ext], kind="stable")]
            groups = np.searchsorted(layout.group[ext], np.arange(GROUPS + 1))
            runs = sample_runs(obs) if every else runs_of(obs.rate_idx[rows], obs.motion.axis_idx[rows],
                                                          obs.motion.rotating[rows])
            shared = max(groups[3 + 2 * a] - groups[1 + 2 * a] for a in range(3))   # rows of the axes' columns
            columns = design_buffer(obs, 4 + groups[1] + shared, rows.size, width)
            columns[0] = 1.0
            if every and st.unit_slope:
                columns[1:4] = st.geo.force
            elif every:
                np.multiply(st.slope, st.geo.force, out=columns[1:4])
            else:
                columns[1:4] = (st.slope * st.geo.force)[:, rows]
            for k, i in enumerate(ext[:groups[1]]):
                self._column(r, i, None if every else rows, params is not None, columns[4 + k])
            for a in range(3):   # each axis's columns into the shared rows, on its runs
                on_axis = [run.samples for run in runs if run.axis == a]
                for k, i in enumerate(ext[groups[1 + 2 * a]:groups[3 + 2 * a]]):
                    self._column(r, i, None if every else rows, params is not None, columns[4 + groups[1] + k], on_axis)
            base = np.array([[layout.index[f"O.{f}.{r}"]] + [layout.index[f"R.{f}.{r}.{c}"] for c in range(3)]
                             for f in range(m)])
            # every sample used: a strided copy of the residuals' column instead of a gather (same values)
            weight = None if obs.whitening is None else obs.whitening.rows(rows, r)
            d = ChannelDesign(columns, obs.rate_idx if every else obs.rate_idx[rows], rows,
                              np.ascontiguousarray(self.resid[:, r]) if every else self.resid[rows, r], base, ext,
                              groups, runs, weight)
            if weight is not None:   # the rows each run reads, whitened as the residuals (each block starts a segment)
                for blk in d.blocks:
                    at = blk.samples
                    columns[:blk.width, at] = filtered(columns[:blk.width, at], weight[0][at], weight[1][at], axis=1)
            G, b = normal_equations(d, p, m)
            designs.append(d)
            grams.append(G)
            rhss.append(b)
        rss = np.einsum("ij,ij->j", self.resid, self.resid)
        return Evaluation(self.pred, self.resid, np.array(grams), np.array(rhss), rss, use.sum(axis=0), tuple(designs))


def evaluate(obs: Observations, beta: np.ndarray, layout: Layout, active: tuple[Candidate, ...],
             clip: tuple[float | None, float | None], structure: Structure, use: np.ndarray) -> Evaluation:
    """Predictions and the Jacobian of every parameter (enabled or not)."""
    return Linearisation(obs, beta, layout, active, clip, structure, use).evaluation()


def weighted(ev: Evaluation, sigma: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    w = 1.0 / sigma**2
    return np.einsum("r,rij->ij", w, ev.gram), np.einsum("r,ri->i", w, ev.rhs)


def solve(G: np.ndarray, b: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, float]:
    """Gauss-Newton step of the parameters ``idx`` and its chi-square reduction
    (Cholesky on the scaled normal equations; least squares if singular)."""
    sub = G[idx[:, None], idx]
    scale = np.sqrt(np.diag(sub))
    scale[scale == 0] = 1.0
    A = sub / np.outer(scale, scale)
    rhs = b[idx] / scale
    # scipy.linalg.cho_factor and cho_solve's LAPACK calls, without their
    # argument handling (about 0.1 ms a call; hundreds of calls a diagnosis)
    factor, info = dpotrf(A, lower=False, overwrite_a=True, clean=False)
    if info == 0:
        step = dpotrs(factor, rhs, lower=False)[0]
    else:  # not positive definite
        step = np.linalg.lstsq(A, rhs, rcond=1e-12)[0]
    step = step / scale
    return step, float(b[idx] @ step)


def rss_after(ev: Evaluation, step: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Per-channel residual sum of squares after a linearised step."""
    gram, rhs = ev.gram[:, idx[:, None], idx], ev.rhs[:, idx]   # the three channels' blocks in one gather each
    return np.array([ev.rss[r] - 2 * step @ rhs[r] + step @ gram[r] @ step for r in range(3)])
