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

from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs

from rotcal.diagnose.candidates import STEP, effects_from
from rotcal.diagnose.geometry import Observations, column_buffer, design_buffer, motion_reuse
from rotcal.diagnose.states import ChannelState, channel_states
from rotcal.model.effects import GainEffect, ScaleEffect, catalogue, effect_named
from rotcal.model.effects.base import Candidate, Channel
from rotcal.model.physics import (
    Effects,
    nonlinearity,
    offset_terms,
    scale_terms,
    scaled,
)


class Layout:
    """Parameter order: offsets O (rate, channel), responsivities R (rate,
    channel, component), then every candidate's parameters."""

    def __init__(self, n_rates: int, candidates: tuple[Candidate, ...]):
        names = [f"O.{f}.{r}" for f in range(n_rates) for r in range(3)]
        names += [f"R.{f}.{r}.{c}" for f in range(n_rates) for r in range(3) for c in range(3)]
        channels: list[tuple[int, ...]] = [(r,) for f in range(n_rates) for r in range(3)]
        channels += [(r,) for f in range(n_rates) for r in range(3) for c in range(3)]
        self.n_base = len(names)
        self.candidates = candidates
        for cand in candidates:
            names += cand.names
            channels += cand.channels
        self.names = tuple(names)
        self.index = {n: i for i, n in enumerate(names)}
        self.n_rates = n_rates
        self.per_channel = [np.array([i for i, ch in enumerate(channels) if r in ch]) for r in range(3)]

    def params(self, cand: Candidate) -> np.ndarray:
        return np.array([self.index[n] for n in cand.names])

    def offsets(self, beta: np.ndarray) -> np.ndarray:
        return beta[: 3 * self.n_rates].reshape(self.n_rates, 3)

    def responsivity(self, beta: np.ndarray) -> np.ndarray:
        return beta[3 * self.n_rates : self.n_base].reshape(self.n_rates, 3, 3)

    def values(self, beta: np.ndarray, active: tuple[Candidate, ...]) -> dict[str, float]:
        return {n: float(beta[self.index[n]]) for c in active for n in c.names}


@dataclass(frozen=True, eq=False)
class ChannelDesign:
    """One channel's Jacobian on its used samples, stored compactly and
    column-major (each column contiguous, as it is computed): column 0 is
    the offset and 1-3 the responsivity of the sample's own rate (their
    parameters are ``base[rate]``), the rest are extensions (``ext``)."""

    columns: np.ndarray    # (4 + k, n_used)
    rate_idx: np.ndarray   # (n_used,), non-decreasing
    rows: np.ndarray       # (n_used,) sample numbers
    resid: np.ndarray      # (n_used,)
    base: np.ndarray       # (m, 4) parameter numbers of O.f.r, R.f.r.x/y/z
    ext: np.ndarray        # (k,) parameter numbers

    @property
    def X(self) -> np.ndarray:
        """The design (n_used, 4 + k), a view."""
        return self.columns.T


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Predictions, residuals and the unweighted normal-equation pieces of
    every channel at one parameter vector (only samples in ``use``)."""

    pred: np.ndarray      # (n, 3)
    resid: np.ndarray     # (n, 3), zero where not used
    gram: np.ndarray      # (3, p, p) per channel J'J
    rhs: np.ndarray       # (3, p) per channel J' resid
    rss: np.ndarray       # (3,)
    n_used: np.ndarray    # (3,)
    designs: tuple[ChannelDesign, ...]


def normal_equations(d: ChannelDesign, p: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    """The full (p, p) J'J and J'r of one channel from its compact design
    (rows sorted by rate, so each rate's block is a view; J'J of a block is
    one BLAS ``syrk`` on the column-major columns, no transposed copy)."""
    k = d.ext.size
    # the channel's own parameters (every rate's base, then the extensions),
    # scattered into the (p, p) matrix once
    own, own_rhs = np.zeros((4 * m + k, 4 * m + k)), np.zeros(4 * m + k)
    ext = slice(4 * m, None)
    cuts = np.searchsorted(d.rate_idx, np.arange(m + 1))
    for f in range(m):
        Cf = d.columns[:, cuts[f]:cuts[f + 1]]
        Gf = Cf @ Cf.T
        bf = Cf @ d.resid[cuts[f]:cuts[f + 1]]
        base = slice(4 * f, 4 * f + 4)
        own[base, base] = Gf[:4, :4]
        own[base, ext] = Gf[:4, 4:]
        own[ext, base] = Gf[4:, :4]
        own[ext, ext] += Gf[4:, 4:]
        own_rhs[base] = bf[:4]
        own_rhs[ext] += bf[4:]
    params = np.concatenate([d.base.ravel(), d.ext])
    G, b = np.zeros((p, p)), np.zeros(p)
    G[params[:, None], params] = own
    b[params] = own_rhs
    return G, b


def with_columns(ev: Evaluation, extra: list[tuple[np.ndarray, np.ndarray]], m: int,
                 obs: Observations | None = None) -> Evaluation:
    """``ev`` with further Jacobian columns: ``extra[r]`` = (parameter
    numbers, columns (n, k)) of channel r, e.g. an offset step's indicator
    (``obs``: the observations whose scratch array can hold a gather of the
    design's columns)."""
    gram, rhs = ev.gram.copy(), ev.rhs.copy()
    for r, (d, (params, columns)) in enumerate(zip(ev.designs, extra)):
        E = columns[d.rows]
        keep = ~np.isin(d.ext, params)  # the design holds these columns as zeros
        kept = 4 + np.flatnonzero(keep)
        if kept.size > 0 and kept[-1] - kept[0] == kept.size - 1:  # a run of columns: a view
            ext_columns = d.columns[kept[0]:kept[-1] + 1]
        else:  # into the scratch array: no fresh pages to fault in
            ext_columns = np.take(d.columns, kept, axis=0,
                                  mode="clip", out=None if obs is None else column_buffer(obs, kept.size)[:, :d.rows.size])
        cross_ext = ext_columns @ E
        gram[r][np.ix_(d.ext[keep], params)] = cross_ext
        gram[r][np.ix_(params, d.ext[keep])] = cross_ext.T
        gram[r][np.ix_(params, params)] = E.T @ E
        rhs[r][params] = E.T @ d.resid
        cuts = np.searchsorted(d.rate_idx, np.arange(m + 1))
        for f in range(m):
            at = slice(cuts[f], cuts[f + 1])
            cross = d.columns[:4, at] @ E[at]
            gram[r][np.ix_(d.base[f], params)] = cross
            gram[r][np.ix_(params, d.base[f])] = cross.T
    return replace(ev, gram=gram, rhs=rhs)


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

    def scale_column(self, effect: ScaleEffect, st: ChannelState, derivative: np.ndarray,
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
        self.resid = np.where(use, obs.y - self.pred, 0.0)
        self.by_name = {n: c for c in layout.candidates for n in c.names}
        self.built: dict[tuple[int, int], np.ndarray] = {}

    def _column(self, r: int, i: int, rows: np.ndarray | None, keep: bool, row: np.ndarray) -> None:
        """Channel r's column of parameter i on the used ``rows`` (None:
        every sample) into ``row``, the design's. ``keep``: kept for a later
        evaluation (the active parameters'); the others are computed into
        the design's row itself when every sample is used (no copy)."""
        column = self.built.get((r, i))
        if column is None:
            name = self.layout.names[i]
            column = self.factors.column(name, self.by_name[name], self.states[r],
                                         None if keep or rows is not None else row)
            if keep:
                self.built[r, i] = column
        if column is row:
            return
        if rows is None:
            np.copyto(row, column)
        else:
            np.take(column, rows, out=row)

    def evaluation(self, params: np.ndarray | None = None) -> Evaluation:
        """The normal equations of the Jacobian's columns of the base
        parameters and the extension parameters ``params`` (None: all);
        the others' rows and columns are zero."""
        obs, layout, use = self.obs, self.layout, self.use
        p, m = len(layout.names), layout.n_rates
        designs, grams, rhss = [], [], []
        width = 4 + max(int((channel >= layout.n_base).sum()) for channel in layout.per_channel)
        for st in self.states:
            r = st.r
            rows = np.flatnonzero(use[:, r])
            every = rows.size == obs.n
            ext = layout.per_channel[r][layout.per_channel[r] >= layout.n_base]
            if params is not None:
                ext = ext[np.isin(ext, params)]
            columns = design_buffer(obs, 4 + ext.size, rows.size, width)
            columns[0] = 1.0
            if every and st.unit_slope:
                columns[1:4] = st.geo.force
            elif every:
                np.multiply(st.slope, st.geo.force, out=columns[1:4])
            else:
                columns[1:4] = (st.slope * st.geo.force)[:, rows]
            for k, i in enumerate(ext):
                self._column(r, i, None if every else rows, params is not None, columns[4 + k])
            base = np.array([[layout.index[f"O.{f}.{r}"]] + [layout.index[f"R.{f}.{r}.{c}"] for c in range(3)]
                             for f in range(m)])
            # every sample used: a strided copy of the residuals' column instead of a gather (same values)
            d = ChannelDesign(columns, obs.rate_idx if every else obs.rate_idx[rows], rows,
                              np.ascontiguousarray(self.resid[:, r]) if every else self.resid[rows, r], base, ext)
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
    return np.array([
        ev.rss[r] - 2 * step @ ev.rhs[r][idx] + step @ ev.gram[r][idx[:, None], idx] @ step for r in range(3)
    ])
