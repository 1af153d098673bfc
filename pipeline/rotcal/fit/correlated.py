"""Segment fits' uncertainties where the noise is correlated from sample to sample.

A segment fit's covariance Sigma (x) (X^T X)^-1 holds for white noise. A
sensor whose digital low-pass filter reaches below its output rate, or whose
bias wanders, correlates successive samples. Least squares on
trigonometric regressors then has, for long records, the variance it would
have under white noise of the noise's spectral density at their frequency
(Grenander 1954, Ann. Math. Statist. 25, 252): the factor on a
coefficient's variance is that density's ratio to the white one's, at
omega = 0 for the offset and a static segment's steps (each step is many
samples long) and at omega = 2 pi rate dt, the angle step per sample, for a
rotation's sine and cosine.

The density comes from the residuals' lag-1 and lag-2 autocorrelations,
taken as white noise plus a first-order autoregression (a filtered or
wandering part): rho_k = rho_1 phi^(k-1), phi = rho_2 / rho_1, at least
rho_1 (no white part) and below 1, so

    F(omega) = 1 + 2 rho_1 (cos omega - phi) / (1 - 2 phi cos omega + phi^2),

(1 + rho) / (1 - rho) at omega = 0 for a plain autoregression. Applied
where rho_1 is significant (beyond ``CORRELATION_Z`` standard errors
1 / sqrt(n)) and positive, never below 1: white noise leaves every fit as
it was. Measured in docs/method.md ("Correlated noise").
"""

from __future__ import annotations

import numpy as np

# White noise gives |rho| beyond 4 / sqrt(n) with probability 6e-5 per channel
CORRELATION_Z = 4.0
# the highest autoregressive order ``autoregressive_density_ratio`` tries (a second-order low-pass at a tenth of the
# sample rate needs about 6)
MAX_AR_ORDER = 20


def grouped_autocorrelation(x: np.ndarray, group: np.ndarray, n_groups: int, run: np.ndarray,
                            use: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The lag-1 and lag-2 autocorrelations (n_groups, columns) of the
    columns of ``x`` (residuals, or samples about their group's mean) in
    each group: the products of samples k apart within one ``run`` (a
    segment, a pose), both in ``use``, over the group's sum of squares
    (NaN where that is 0)."""
    used = np.ones(x.shape, bool) if use is None else use
    columns = range(x.shape[1])
    square = np.stack([np.bincount(group, np.where(used[:, r], x[:, r] ** 2, 0.0), n_groups) for r in columns], axis=1)
    lags = []
    for k in (1, 2):
        pair = (run[k:] == run[:-k])[:, None] & used[k:] & used[:-k]
        products = np.stack([np.bincount(group[k:], np.where(pair[:, r], x[k:, r] * x[:-k, r], 0.0), n_groups)
                             for r in columns], axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            lags.append(products / square)
    return lags[0], lags[1]


def density_ratio(lag1: np.ndarray, lag2: np.ndarray | None, n: np.ndarray | int, omega: float) -> np.ndarray:
    """F(omega), elementwise, from lag-1 and lag-2 autocorrelations over
    ``n`` samples each (lag 2 None: a plain autoregression); 1 where lag 1
    is not significant and positive, n at most."""
    rho = np.nan_to_num(np.asarray(lag1, float))
    on = rho > CORRELATION_Z / np.sqrt(np.maximum(n, 1))
    rho = np.where(on, np.minimum(rho, 0.999), 0.0)
    second = rho**2 if lag2 is None else np.nan_to_num(np.asarray(lag2, float))
    phi = np.clip(np.divide(second, rho, out=np.zeros_like(rho), where=on), rho, 0.999)
    c = np.cos(omega)
    # at most n: n samples' mean varies no more than one sample does, however correlated
    return np.clip(1 + 2 * rho * (c - phi) / (1 - 2 * phi * c + phi**2), 1.0, np.maximum(n, 1))


def noise_scales(lag1: np.ndarray, lag2: np.ndarray | None, n: int, step_rad: float) -> tuple[np.ndarray, float] | None:
    """The factors on the standard deviations of a fit's nine coefficients
    (channel-major C, A, B) and of its rate, from each channel's residual
    lag-1 and lag-2 autocorrelations over ``n`` samples and the angle step
    ``step_rad`` per sample (2 pi rate dt, 0 for a static segment); None
    where no channel's lag 1 is significant and positive."""
    at_zero = density_ratio(lag1, lag2, n, 0.0)
    if np.all(at_zero == 1.0):
        return None
    at_rate = density_ratio(lag1, lag2, n, step_rad)
    return np.sqrt(np.column_stack([at_zero, at_rate, at_rate])).ravel(), float(np.sqrt(at_rate.max()))


def autoregressive_density_ratio(pieces: list[np.ndarray], max_order: int = MAX_AR_ORDER) -> float:
    """F(0) of the noise in ``pieces`` (each a run of consecutive samples,
    taken about its mean) from the autoregression x_t = sum a_k x_t-k + e_t
    that describes them: least squares on the samples with ``max_order``
    predecessors in their piece (the covariance method, Percival & Walden
    1993 section 9.7), of the order 0..``max_order`` with the least
    AIC = N log v_p + 2 p; F(0) = v_p / (1 - sum a_k)^2 over the samples'
    variance, between 1 and the longest piece's length. Where the lag-1 and
    lag-2 form above does not hold (a filter of higher order: a fourth-order
    low-pass at 0.05 of the rate, whose autocorrelation turns negative
    within tens of samples, read F(0) 90 for 9.7 by it), the autoregression
    follows the spectrum down to zero frequency."""
    runs = [p - p.mean() for p in pieces if p.size > 10 * (max_order + 1)]
    if not runs:
        return 1.0
    lagged = np.concatenate([np.stack([p[max_order - k:p.size - k] for k in range(max_order + 1)], axis=1) for p in runs])
    y, past = lagged[:, 0], lagged[:, 1:]
    x = np.concatenate(runs)
    variance = float(x @ x) / x.size
    if variance <= 0:
        return 1.0
    best, best_v = akaike_autoregression(y, past)
    ratio = best_v / (1.0 - float(best.sum())) ** 2 / variance
    return float(np.clip(ratio, 1.0, max(p.size for p in runs)))


def akaike_autoregression(y: np.ndarray, past: np.ndarray) -> tuple[np.ndarray, float]:
    """(a_1..a_p, the innovations' mean square v_p) of the autoregression
    y_t = sum a_k y_t-k + e_t on the lagged samples ``past`` (rows, max
    order: column k-1 holds y_t-k), of the order 0..max with the least
    AIC = N log v_p + 2 p; every order's least squares from one Gram
    matrix (one pass over the samples, not one per order)."""
    gram, cross, total = past.T @ past, past.T @ y, float(y @ y)
    best, best_aic, best_v = np.zeros(0), y.size * np.log(max(total / y.size, 1e-300)), total / y.size
    for p in range(1, past.shape[1] + 1):
        try:
            a = np.linalg.solve(gram[:p, :p], cross[:p])
        except np.linalg.LinAlgError:
            break
        v = (total - float(a @ cross[:p])) / y.size
        if not np.isfinite(v) or v <= 0:
            break
        aic = y.size * np.log(v) + 2 * p
        if aic < best_aic:
            best, best_aic, best_v = a, aic, v
    return best, best_v
