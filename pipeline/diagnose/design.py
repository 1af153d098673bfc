"""One channel's Jacobian on its used samples, stored compactly, and the
normal-equation pieces made from it (``rotcal.diagnose.model`` builds it).

The samples are sorted by rate and cut into runs of one rate and one table
axis (``geometry.runs_of``). Many extension columns are zero off one axis's
samples (an axis tilt, a rate ripple, a centripetal offset: their
``Support``), so the design holds the columns of the three axes' effects in
shared rows, each axis's on its own runs, and every product is taken run by
run over the columns that can be nonzero there: on the default plan a
channel's 21 extension columns fill 11 rows (6 for every axis, 5 shared by
the axes), and a rotation run reads 15 of its 25 columns.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from itertools import groupby

import numpy as np

from rotcal.diagnose.geometry import Run
from rotcal.model.effects.base import Support

GROUPS = 8  # of ``support_group``


def support_group(support: Support) -> int:
    """The order of a design's extension columns: those nonzero on every
    sample, on every rotation sample, then per axis on its samples and on its
    rotation samples."""
    return int(support.rotating) if support.axis is None else 2 + 2 * support.axis + int(support.rotating)


@dataclass(frozen=True)
class Block:
    """Samples of one rate (a run, or consecutive runs) and the design's
    rows they read: the base and every (rotation) sample's extensions
    (``lead``, rows = positions among base and extensions); their axis's
    extensions (their rotation samples' too when they rotate): ``axis_rows``
    of the design, at positions ``on``."""

    rate: int
    samples: slice
    lead: slice
    axis_rows: slice
    on: slice


@dataclass(frozen=True, eq=False)
class ChannelDesign:
    """One channel's Jacobian on its used samples, column-major (each column
    contiguous, as it is computed): row 0 is the offset and 1-3 the
    responsivity of the sample's own rate (their parameters are
    ``base[rate]``); then the extensions (``ext``, in the order of their
    ``support_group``) of every axis, then those of one axis, each axis's
    in the same rows on its own runs (``blocks``). What no run reads is
    left as it was."""

    columns: np.ndarray    # (4 + k', n_used), k' <= k
    rate_idx: np.ndarray   # (n_used,), non-decreasing
    rows: np.ndarray       # (n_used,) sample numbers
    resid: np.ndarray      # (n_used,)
    base: np.ndarray       # (m, 4) parameter numbers of O.f.r, R.f.r.x/y/z
    ext: np.ndarray        # (k,) parameter numbers
    groups: np.ndarray     # (GROUPS + 1,) extension group g is ext[groups[g]:groups[g + 1]]
    runs: list[Run]        # the used samples' runs of one rate and axis

    @cached_property
    def blocks(self) -> list[Block]:
        """What each run reads; consecutive runs of a rate that read the
        same rows and no axis's merged (one product, not three, where no
        axis's extension is in the design)."""
        g, out = self.groups, list[Block]()
        for run in self.runs:
            a = 2 + 2 * run.axis
            count = g[a + 1 + run.rotating] - g[a]
            lead, start = slice(0, 4 + g[1 + run.rotating]), run.samples.start
            last = out[-1] if out else None
            if last and not count and last.on.stop == last.on.start and (last.rate, last.lead) == (run.rate, lead):
                start = out.pop().samples.start
            out.append(Block(run.rate, slice(start, run.samples.stop), lead,
                             slice(4 + g[2], 4 + g[2] + count), slice(4 + g[a], 4 + g[a] + count)))
        return out

    def transposed_times(self, E: np.ndarray) -> np.ndarray:
        """J'E (4 m + k, q) of the channel's own parameters (every rate's
        base, then the extensions), E (n_used, q)."""
        m = self.base.shape[0]
        out = np.zeros((4 * m + self.ext.size, E.shape[1]))
        for b in self.blocks:
            lead_part = self.columns[b.lead, b.samples] @ E[b.samples]
            out[4 * b.rate:4 * b.rate + 4] += lead_part[:4]
            out[4 * m:4 * m + b.lead.stop - 4] += lead_part[4:]
            out[4 * m + b.on.start - 4:4 * m + b.on.stop - 4] += self.columns[b.axis_rows, b.samples] @ E[b.samples]
        return out

    @property
    def X(self) -> np.ndarray:
        """The design (n_used, 4 + k) in full, each column zero where no
        run reads it (a copy, for checks)."""
        X = np.zeros((self.rows.size, 4 + self.ext.size))
        for b in self.blocks:
            X[b.samples, b.lead] = self.columns[b.lead, b.samples].T
            X[b.samples, b.on] = self.columns[b.axis_rows, b.samples].T
        return X


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
    """The full (p, p) J'J and J'r of one channel from its compact design,
    run by run (``ChannelDesign.blocks``): a run's columns are read once,
    then from cache. Against one BLAS ``syrk`` per rate over every column
    (the rows sorted by rate, so a rate's block is a view), about a third of
    the multiplications on the default plan."""
    k = d.ext.size
    # the channel's own parameters (every rate's base, then the extensions),
    # scattered into the (p, p) matrix once
    own, own_rhs = np.zeros((4 * m + k, 4 * m + k)), np.zeros(4 * m + k)
    ext = slice(4 * m, None)
    for f, rate_blocks in groupby(d.blocks, key=lambda block: block.rate):
        Gf, bf = np.zeros((4 + k, 4 + k)), np.zeros(4 + k)
        for blk in rate_blocks:
            at, lead, on = blk.samples, blk.lead, blk.on
            A = d.columns[lead, at]
            Gf[lead, lead] += A @ A.T
            bf[lead] += A @ d.resid[at]
            if on.stop > on.start:
                B = d.columns[blk.axis_rows, at]
                Gf[lead, on] += A @ B.T
                Gf[on, on] += B @ B.T
                bf[on] += B @ d.resid[at]
        Gf[4 + d.groups[2]:, :4 + d.groups[2]] = Gf[:4 + d.groups[2], 4 + d.groups[2]:].T   # the axes' products filled one side
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


def with_columns(ev: Evaluation, extra: list[tuple[np.ndarray, np.ndarray]]) -> Evaluation:
    """``ev`` with further Jacobian columns: ``extra[r]`` = (parameter
    numbers, columns (n, q)) of channel r, e.g. an offset step's indicator."""
    gram, rhs = ev.gram.copy(), ev.rhs.copy()
    for r, (d, (params, columns)) in enumerate(zip(ev.designs, extra)):
        E = columns[d.rows]
        own = np.concatenate([d.base.ravel(), d.ext])
        keep = ~np.isin(own, params)  # the design holds these columns as zeros
        cross = d.transposed_times(E)[keep]
        gram[r][np.ix_(own[keep], params)] = cross
        gram[r][np.ix_(params, own[keep])] = cross.T
        gram[r][np.ix_(params, params)] = E.T @ E
        rhs[r][params] = E.T @ d.resid
    return replace(ev, gram=gram, rhs=rhs)
