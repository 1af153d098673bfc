"""Whether the noise differs between a dataset's parts, and the whitening
that makes it equal.

Every test of the diagnosis takes one noise level per channel. A table that
vibrates more at its higher rates breaks that: the noisy segments' residuals
then look like misfits, tones and steps (docs/method.md, "Tests and their
false-alarm rates"). So each channel's noise is estimated in every group of
one rate and one table axis, from the differences of successive residuals of
the selected model (von Neumann 1941; a slow misfit, such as a concealed
effect, cancels in them), and where Bartlett's test rejects equal variances
each sample's residual and Jacobian row are scaled by the pooled noise over
its group's: weighted least squares, whose tests are those of equal noise.
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.geometry import Observations, sample_runs


def group_noise(obs: Observations, resid: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(group of each sample, variance (g, 3), degrees of freedom (g, 3)) of
    the residuals ``resid`` in each group of one rate and axis: the von
    Neumann estimate sum (e_i+1 - e_i)^2 / 2m over the m differences within
    a segment between used samples, whose variance 2 sigma^4 / nu gives
    nu = 2 m^2 / (3 m - 1) (the differences are correlated, -1/2 at lag 1)."""
    keys = [(run.rate, run.axis) for run in sample_runs(obs)]
    names = {key: i for i, key in enumerate(dict.fromkeys(keys))}
    group = np.repeat([names[k] for k in keys], [run.samples.stop - run.samples.start for run in sample_runs(obs)])
    pair = ((obs.segment[1:] == obs.segment[:-1]) & (group[1:] == group[:-1]))[:, None] & use[1:] & use[:-1]
    d2 = np.where(pair, np.diff(resid, axis=0) ** 2, 0.0)
    m = np.stack([np.bincount(group[1:], pair[:, r], len(names)) for r in range(3)], axis=1)
    ss = np.stack([np.bincount(group[1:], d2[:, r], len(names)) for r in range(3)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return group, ss / (2 * m), np.where(m > 0, 2 * m**2 / np.maximum(3 * m - 1, 1), 0.0)


def bartlett(variance: np.ndarray, dof: np.ndarray) -> float:
    """P-value of Bartlett's test of equal variances (Bartlett 1937; NIST
    e-Handbook 1.3.5.7) from variance estimates with ``dof`` degrees of
    freedom each (those with none left out): chi-square(k - 1)."""
    on = dof > 0
    s2, nu = variance[on], dof[on]
    if s2.size < 2:
        return 1.0
    total = nu.sum()
    pooled = (nu * s2).sum() / total
    c = 1 + ((1 / nu).sum() - 1 / total) / (3 * (s2.size - 1))
    stat = (total * np.log(pooled) - (nu * np.log(s2)).sum()) / c
    return chi2_sf(stat, s2.size - 1)


def whitening(obs: Observations, resid: np.ndarray, use: np.ndarray, alpha: float) -> np.ndarray | None:
    """Each sample's factor (n, 3), the pooled noise over its group's, in
    the channels whose groups' noise differs (Bartlett at ``alpha``,
    Bonferroni over channels; 1 in the others); None where no channel's
    does, or where the noise is at the numerical floor (noise-free data)."""
    group, variance, dof = group_noise(obs, resid, use)
    floor = obs.noise_floor**2
    factor = np.ones_like(obs.y)
    whitened = False
    for r in range(3):
        on = dof[:, r] > 0
        if not np.all(variance[on, r] > floor[r]) or bartlett(variance[:, r], dof[:, r]) >= alpha / 3:
            continue
        pooled = (dof[on, r] * variance[on, r]).sum() / dof[on, r].sum()
        scale = np.where(on, np.sqrt(pooled / np.where(on, variance[:, r], 1.0)), 1.0)
        factor[:, r] = scale[group]
        whitened = True
    return factor if whitened else None
