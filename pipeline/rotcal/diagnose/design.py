"""One channel's Jacobian on its used samples, stored compactly, and the
normal-equation pieces made from it (``rotcal.diagnose.model`` builds it).

The samples are sorted by rate and cut into runs of one rate and one table
axis (``geometry.runs_of``). Many extension columns are zero off one axis's
samples (an axis tilt, a rate ripple, a centripetal offset: their
``Support``), so the design holds the columns of the three axes' effects in
shared rows, each axis's on its own runs, and every product is taken run by
run over the columns that can be nonzero there, the design's first rows: on
the default plan a channel's 21 extension columns fill 11 rows (6 for every
axis, 5 shared by the axes), and a rotation run reads 15 of its 25 columns.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property
from itertools import groupby

import numpy as np

from rotcal.diagnose.geometry import Run, filtered
from rotcal.model.effects.base import Support

GROUPS = 7  # of ``support_group``


def support_group(support: Support) -> int:
    """The order of a design's extension columns: those of every axis, then
    per axis those nonzero on its samples, on its rotation samples; so a
    run's columns are the design's first rows."""
    return 0 if support.axis is None else 1 + 2 * support.axis + int(support.rotating)


@dataclass(frozen=True)
class Block:
    """Samples of one rate (a run, or consecutive runs of no axis's
    extension) and the columns they read: the design's first ``width``
    rows, the base's and every axis's extensions', then their axis's
    extensions' (its rotation samples' too when they rotate), at positions
    ``on`` among base and extensions."""

    rate: int
    samples: slice
    width: int
    on: slice


@dataclass(frozen=True, eq=False)
class ChannelDesign:
    """One channel's Jacobian on its used samples, column-major (each column
    contiguous, as it is computed): row 0 is the offset and 1-3 the
    responsivity of the sample's own rate (their parameters are
    ``base[rate]``); then the extensions (``ext``, in the order of their
    ``support_group``) of every axis (``lead`` rows in all), then those of
    one axis, each axis's in the same rows on its own runs (``blocks``).
    What no run reads is left as it was."""

    columns: np.ndarray    # (4 + k', n_used), k' <= k
    rate_idx: np.ndarray   # (n_used,), non-decreasing
    rows: np.ndarray       # (n_used,) sample numbers
    resid: np.ndarray      # (n_used,)
    base: np.ndarray       # (m, 4) parameter numbers of O.f.r, R.f.r.x/y/z
    ext: np.ndarray        # (k,) parameter numbers
    groups: np.ndarray     # (GROUPS + 1,) extension group g is ext[groups[g]:groups[g + 1]]
    runs: list[Run]        # the used samples' runs of one rate and axis
    weight: tuple[np.ndarray, np.ndarray] | None = None   # the rows' whitening (scale, phi; ``Whitening.rows``)

    def rows_of(self, columns: np.ndarray) -> np.ndarray:
        """Further columns (n, q) of every sample as this design's rows:
        its used samples', whitened as its own."""
        E = columns[self.rows]
        return E if self.weight is None else filtered(E, self.weight[0][:, None], self.weight[1][:, None])

    @property
    def lead(self) -> int:
        return 4 + int(self.groups[1])

    @cached_property
    def blocks(self) -> list[Block]:
        """What each run reads; consecutive runs of a rate that read no
        axis's extension merged (one product, where no axis's is in the
        design)."""
        g, lead, out = self.groups, self.lead, list[Block]()
        for run in self.runs:
            a = 1 + 2 * run.axis
            count = int(g[a + 1 + run.rotating] - g[a])
            start = run.samples.start
            if out and not count and out[-1].width == lead and out[-1].rate == run.rate:
                start = out.pop().samples.start
            out.append(Block(run.rate, slice(start, run.samples.stop), lead + count, slice(4 + g[a], 4 + g[a] + count)))
        return out

    def transposed_times(self, E: np.ndarray) -> np.ndarray:
        """J'E (4 m + k, q) of the channel's own parameters (every rate's
        base, then the extensions), E (n_used, q)."""
        m, lead = self.base.shape[0], self.lead
        out = np.zeros((4 * m + self.ext.size, E.shape[1]))
        for b in self.blocks:
            part = self.columns[:b.width, b.samples] @ E[b.samples]
            out[4 * b.rate:4 * b.rate + 4] += part[:4]
            out[4 * m:4 * m + lead - 4] += part[4:lead]
            out[4 * m + b.on.start - 4:4 * m + b.on.stop - 4] += part[lead:]
        return out

    @property
    def X(self) -> np.ndarray:
        """The design (n_used, 4 + k) in full, each column zero where no
        run reads it (a copy, for checks)."""
        X, lead = np.zeros((self.rows.size, 4 + self.ext.size)), self.lead
        for b in self.blocks:
            X[b.samples, :lead] = self.columns[:lead, b.samples].T
            X[b.samples, b.on] = self.columns[lead:b.width, b.samples].T
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
    one product per run (``ChannelDesign.blocks``: one BLAS ``syrk`` on the
    column-major columns, no transposed copy). Against one per rate over
    every column (the rows sorted by rate, a rate's block is a view), 15 of
    25 columns read on the default plan: the products are as fast as the
    columns are read (about 5 GB/s)."""
    k, lead = d.ext.size, d.lead
    # the channel's own parameters (every rate's base, then the extensions),
    # scattered into the (p, p) matrix once
    own, own_rhs = np.zeros((4 * m + k, 4 * m + k)), np.zeros(4 * m + k)
    ext = slice(4 * m, None)
    for f, rate_blocks in groupby(d.blocks, key=lambda block: block.rate):
        Gf, bf = np.zeros((4 + k, 4 + k)), np.zeros(4 + k)
        for blk in rate_blocks:
            X = d.columns[:blk.width, blk.samples]
            G, b = X @ X.T, X @ d.resid[blk.samples]
            Gf[:lead, :lead] += G[:lead, :lead]
            Gf[:lead, blk.on] += G[:lead, lead:]
            Gf[blk.on, :lead] += G[lead:, :lead]
            Gf[blk.on, blk.on] += G[lead:, lead:]
            bf[:lead] += b[:lead]
            bf[blk.on] += b[lead:]
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
        E = d.rows_of(columns)
        own = np.concatenate([d.base.ravel(), d.ext])
        keep = ~np.isin(own, params)  # the design holds these columns as zeros
        cross = d.transposed_times(E)[keep]
        gram[r][np.ix_(own[keep], params)] = cross
        gram[r][np.ix_(params, own[keep])] = cross.T
        gram[r][np.ix_(params, params)] = E.T @ E
        rhs[r][params] = E.T @ d.resid
    return replace(ev, gram=gram, rhs=rhs)
