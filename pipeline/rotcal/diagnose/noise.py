"""Whether the noise differs between a dataset's parts or is correlated
from sample to sample, and the whitening that makes it white and equal.

Every test of the diagnosis takes one white noise level per channel. A
table that vibrates more at its higher rates breaks that, and so does a
sensor whose filter correlates successive samples: the residuals then look
like misfits, tones, harmonics and steps (docs/method.md, "Tests and their
false-alarm rates"). So each channel's noise is estimated in every group of
one rate and one table axis from the selected model's residuals: its level
from the differences of successive residuals (von Neumann 1941; a slow
misfit, such as a concealed effect, cancels in them), its correlation from
their lag-1 and lag-2 autocorrelations. Where the correlation is
significant, residuals and Jacobian rows are filtered (first order, white
at zero frequency); where Bartlett's test rejects equal levels, they are
scaled by the pooled noise over their group's: generalised least squares,
whose tests are those of white, equal noise.
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.geometry import Observations, Whitening, sample_runs
from rotcal.fit.correlated import density_ratio, grouped_autocorrelation


def group_noise(obs: Observations, resid: np.ndarray, use: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(group of each sample, variance (g, 3), degrees of freedom (g, 3)) of
    the residuals ``resid`` in each group of one rate and axis: the von
    Neumann estimate sum (e_i+1 - e_i)^2 / 2m over the m differences within
    a run (``Observations.run``) between used samples, whose variance 2 sigma^4 / nu gives
    nu = 2 m^2 / (3 m - 1) (the differences are correlated, -1/2 at lag 1)."""
    keys = [(run.rate, run.axis) for run in sample_runs(obs)]
    names = {key: i for i, key in enumerate(dict.fromkeys(keys))}
    group = np.repeat([names[k] for k in keys], [run.samples.stop - run.samples.start for run in sample_runs(obs)])
    pair = ((obs.run[1:] == obs.run[:-1]) & (group[1:] == group[:-1]))[:, None] & use[1:] & use[:-1]
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


def whitening(obs: Observations, resid: np.ndarray, use: np.ndarray, alpha: float) -> Whitening | None:
    """The transform that makes the residuals' noise white and equal
    (``geometry.Whitening``): in each group of one rate and axis whose
    residuals are correlated from sample to sample (``fit.correlated``: lag
    1 positive beyond 4 standard errors; the noise density's ratio F(0) to
    white at zero frequency from lags 1 and 2), the first-order filter whose
    output is white at zero frequency, where the signals are: phi =
    (F(0) - 1) / (F(0) + 1) (rho for a plain autoregression), at most 0.95;
    in the channels whose groups' noise differs (Bartlett at ``alpha``,
    Bonferroni over channels, on the marginal variances: the differences'
    over 1 - rho where filtered), each sample scaled by the pooled noise
    over its group's.
    None where neither applies, or where the noise is at the numerical floor
    (noise-free data)."""
    group, variance, dof = group_noise(obs, resid, use)
    # a run lies in one group of rate and axis: pairs within a run are within its group
    lag1, lag2 = grouped_autocorrelation(resid, group, variance.shape[0], obs.run, use)
    # the filter whose output is white at zero frequency, where the signals are: (1 - phi) / (1 + phi) = 1 / F(0)
    ratio = density_ratio(lag1, lag2, np.maximum(dof, 1), 0.0)
    filtering = (dof > 0) & (ratio > 1.0)
    phi = np.where(filtering, np.minimum((ratio - 1) / (ratio + 1), 0.95), 0.0)
    variance = np.where(filtering, variance / (1 - np.minimum(np.nan_to_num(lag1), 0.999)), variance)
    floor = obs.noise_floor**2
    scale = np.ones_like(obs.y)
    for r in range(3):
        on = dof[:, r] > 0
        if not np.all(variance[on, r] > floor[r]) or bartlett(variance[:, r], dof[:, r]) >= alpha / 3:
            continue
        pooled = (dof[on, r] * variance[on, r]).sum() / dof[on, r].sum()
        scale[:, r] = np.where(on, np.sqrt(pooled / np.where(on, variance[:, r], 1.0)), 1.0)[group]
    if not filtering.any() and np.all(scale == 1.0):
        return None
    starts = np.r_[True, obs.run[1:] != obs.run[:-1]]
    return Whitening(scale, np.where(starts[:, None], 0.0, phi[group]))
