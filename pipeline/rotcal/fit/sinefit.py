"""Four-parameter sine fit of a constant-rotation segment against its own
phase, for segments without an angle reference.

All three channels share one rate f (the table's), so the model is

    R_r(t) = C_r + A_r sin(theta) + B_r cos(theta),   theta = 360 f (t - t_ref),

the four-parameter fit of IEEE Std 1057-2017 (4.1.2), with the frequency
common to three channels. The rate comes first from the spectrum (the peak of
the channels' summed periodogram, interpolated), then from the least-squares
minimum of the residual over f (variable projection: for each f, C, A, B
are linear). ``t_ref`` is the mean sample time, which decorrelates f from
A and B. The covariance of the ten parameters is the inverse of the Fisher
information with the residual covariance between channels (as in
``rotcal.fit.segments``); the (C, A, B) block therefore carries the rate's
uncertainty too.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rotcal.fit.segments import SegmentFit, angle_step, design, linear_fit, residual_stats, widened


@dataclass(frozen=True, eq=False)
class SineFit:
    """The rate and its uncertainty, the phase reference, and the segment
    fit (coefficients channel x (C, A, B) against theta = 360 rate (t -
    t_ref), their 9 x 9 covariance, residual statistics; its segment number
    is -1 until the segment has one)."""

    rate_hz: float
    rate_u_hz: float
    t_ref_ns: int
    fit: SegmentFit

    @property
    def determined(self) -> bool:
        """Whether the ten parameters are determined: finite, with variances
        >= 0. A few samples (a labelled rotation cut short) make the
        information matrix near singular and its inverse no covariance."""
        variances = np.append(np.diag(self.fit.cov), self.rate_u_hz)
        return bool(np.isfinite(self.fit.coef).all() and np.isfinite(variances).all() and (variances >= 0).all())

    @property
    def coef(self) -> np.ndarray:
        return self.fit.coef

    @property
    def cov(self) -> np.ndarray:
        return self.fit.cov

    @property
    def sigma(self) -> np.ndarray:
        return self.fit.sigma

    def theta_deg(self, t_ns: np.ndarray) -> np.ndarray:
        return 360.0 * self.rate_hz * (t_ns - self.t_ref_ns) / 1e9

    def model(self, t_ns: np.ndarray) -> np.ndarray:
        return design(self.theta_deg(t_ns)) @ self.coef.T


def spectral_rate(t_s: np.ndarray, y: np.ndarray, f_low: float, f_high: float, oversample: int = 8) -> float:
    """The frequency in [f_low, f_high] with the most power summed over the
    channels: periodogram of the data resampled on a regular grid, zero
    padded ``oversample`` times, peak refined by a parabola through the
    three highest bins (log power)."""
    dt = float(np.median(np.diff(t_s)))
    grid = np.arange(t_s[0], t_s[-1], dt)
    resampled = np.column_stack([np.interp(grid, t_s, y[:, r]) for r in range(y.shape[1])])
    resampled -= resampled.mean(axis=0)
    nfft = int(2 ** np.ceil(np.log2(grid.size * oversample)))
    power = (np.abs(np.fft.rfft(resampled, nfft, axis=0)) ** 2).sum(axis=1)
    freq = np.fft.rfftfreq(nfft, dt)
    band = np.flatnonzero((freq >= f_low) & (freq <= f_high))
    if band.size == 0:
        return 0.5 * (f_low + f_high)
    k = band[np.argmax(power[band])]
    if 0 < k < freq.size - 1:
        a, b, c = np.log(power[k - 1 : k + 2] + 1e-300)
        shift = 0.5 * (a - c) / (a - 2 * b + c) if a - 2 * b + c < 0 else 0.0
        return float(freq[k] + shift * (freq[1] - freq[0]))
    return float(freq[k])


def _rss(rate_hz: float, tau_s: np.ndarray, y: np.ndarray, yy: float) -> float:
    """Residual sum of squares of the best C, A, B at ``rate_hz`` (normal equations)."""
    x = design(360.0 * rate_hz * tau_s)
    xty = x.T @ y
    return yy - float(np.sum(xty * np.linalg.solve(x.T @ x, xty)))


def fit_sine(t_ns: np.ndarray, y: np.ndarray, rate_guess_hz: float, search: bool = True) -> SineFit:
    """Rate, coefficients and covariance of one constant-rotation segment.

    With ``search``, the spectrum within +-30 % of ``rate_guess_hz`` gives
    the start; without, the guess must already be within a twentieth of the
    segment's frequency resolution 1 / duration (a previous fit's rate).
    """
    t_ref = int(np.round(t_ns.mean()))
    if t_ns.size < 4 or not np.median(np.diff(t_ns)) > 0:  # ten parameters need four samples of three channels, and a sample interval
        return SineFit(rate_guess_hz, float("nan"), t_ref, SegmentFit.failed(-1, t_ns.size, "too few samples", rate_guess_hz))
    tau_s = (t_ns - t_ref) / 1e9
    resolution = 1.0 / max(float(tau_s[-1] - tau_s[0]), 1e-9)
    centred = y - y.mean(axis=0)  # the offset is fitted anyway; centring keeps the sums well conditioned
    yy = float(np.sum(centred**2))
    best = rate_guess_hz
    if search:
        guess = spectral_rate(tau_s, y, 0.7 * rate_guess_hz, 1.3 * rate_guess_hz)
        grid = guess + resolution * np.linspace(-0.5, 0.5, 21)
        grid = grid[grid > 0]
        best = grid[int(np.argmin([_rss(f, tau_s, centred, yy) for f in grid]))]
    step = resolution / 20
    from scipy.optimize import minimize_scalar  # here: only segments of unknown rate need scipy.optimize (0.1 s to import)
    rate = float(minimize_scalar(_rss, bounds=(best - step, best + step), args=(tau_s, centred, yy), method="bounded",
                                 options={"xatol": 1e-12 * max(best, 1e-12)}).x)
    x = design(360.0 * rate * tau_s)
    coef, _, resid = linear_fit(x, y)
    n = t_ns.size
    sigma2 = resid.T @ resid / max(n - 10 / 3, 1)
    info_inv = np.linalg.inv(sigma2)
    # d/d(rate) of A sin(theta) + B cos(theta), theta = 2 pi rate tau
    d = 2 * np.pi * tau_s[:, None] * (coef[:, 1][None, :] * x[:, 2:3] - coef[:, 2][None, :] * x[:, 1:2])
    h = x.T @ d  # (3 coefficients, 3 channels)
    info = np.zeros((10, 10))
    info[:9, :9] = np.kron(info_inv, x.T @ x)
    info[:9, 9] = (h @ info_inv).T.ravel()
    info[9, :9] = info[:9, 9]
    info[9, 9] = float(np.einsum("ir,rs,is->", d, info_inv, d))
    cov = np.linalg.inv(info)
    rms, max_abs, lag1, lag2 = residual_stats(resid)
    fit = SegmentFit(-1, "ok", None, n, coef, cov[:9, :9], np.sqrt(np.diag(sigma2)), rms, max_abs, lag1, rate,
                     float(np.sqrt(cov[9, 9])), lag2=lag2)
    fit = widened(fit, angle_step(rate, int(t_ns[0]), int(t_ns[-1]), n))  # for noise correlated between samples
    return SineFit(rate, fit.u_rate_fit_hz, t_ref, fit)
