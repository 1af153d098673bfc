"""Scans of the final residuals against the recording's noise model: the
segments' misfits (Geist 2017 section 3 consistency, trends within a
segment) and the static steps' samples (Geist 2017 Appendix B).

Both tests took the noise as white. Under a coloured noise (a sensor's
filter, a wandering bias) a segment's constant, sine terms and trend scatter
more than white noise of the same level would let them, and successive
samples are correlated: noise, which the uncertainties already carry, read
as a misfit. So each statistic is taken against the noise model the fits
measured:

- a segment's constant and first-harmonic misfit against its fit's
  covariance of (C, A, B) (``fits`` table: the spectrum's density ratios at
  zero frequency and at the rotation's, and the offsets' wander floor,
  ``fit.spectrum`` and ``fit.wander``), a trend against the residual level
  times the density ratio near zero frequency (Grenander 1954: least
  squares on a slow regressor has the variance white noise of the density
  at its frequency would give);
- the static steps' samples prewhitened by the autoregression that
  describes the recording's residuals (least squares within segments,
  order by Akaike's criterion, at most ``MAX_AR_ORDER``): what is left correlated, or non-normal, is not the
  sensor's noise.

Under white noise the fits' covariances are sigma^2 (X^T X)^-1 and the
autoregression's order is 0, so the tests are the white ones.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl
from scipy.special import ndtr

from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.scans import Residuals, Unexplained, _describe, _segment_chi2, _segment_grams, _used_segments, normal_p, p_is
from rotcal.fit.correlated import akaike_autoregression
from rotcal.model.physics import CHANNELS

# the largest variance of a least-squares slope over a record of duration T that a first-order
# Gauss-Markov term of stationary sd q gives, times T^2 / q^2 (at a correlation time of 0.32 T; a random
# walk whose offsets scatter by q between segments gives less): a slow wander's share of a segment's trend
WANDER_SLOPE = 2.45
# the highest autoregressive order the static-step test prewhitens with (a second-order low-pass at a
# tenth of the sample rate needs about 6; each order costs the steps one sample)
MAX_AR_ORDER = 12


@dataclass(frozen=True, eq=False)
class SegmentNoise:
    """Per fitted segment and channel: the fit's covariance of (C, A, B)
    (3, 3, 3: channel, 3 x 3), its residual level and its noise density's
    ratio to white near zero frequency and the offsets' wander floor between
    segments (``fits`` table columns)."""

    cov: dict[int, np.ndarray]
    sigma: dict[int, np.ndarray]
    ratio_zero: dict[int, np.ndarray]
    floor: dict[int, np.ndarray]
    samples: dict[int, np.ndarray] = field(default_factory=dict)

    @classmethod
    def from_fits(cls, fits: pl.DataFrame) -> SegmentNoise:
        cov: dict[int, np.ndarray] = {}
        sigma: dict[int, np.ndarray] = {}
        ratio: dict[int, np.ndarray] = {}
        floor: dict[int, np.ndarray] = {}
        samples: dict[int, np.ndarray] = {}
        rank = {c: i for i, c in enumerate(CHANNELS)}
        columns = ["segment", "channel", "sigma", "noise_ratio_zero", "offset_floor", "n_samples"] + [f"cov_{c}" for c in CHANNELS]
        for row in fits.filter(pl.col("status") == "ok").select(columns).iter_rows(named=True):
            seg, r = int(row["segment"]), rank[row["channel"]]
            own = row[f"cov_{row['channel']}"]
            cov.setdefault(seg, np.full((3, 3, 3), np.nan))[r] = (np.asarray(own, float).reshape(3, 3)
                                                                  if own is not None and len(own) == 9 else np.nan)
            sigma.setdefault(seg, np.full(3, np.nan))[r] = np.nan if row["sigma"] is None else row["sigma"]
            f0 = row["noise_ratio_zero"]
            ratio.setdefault(seg, np.ones(3))[r] = f0 if f0 is not None and np.isfinite(f0) and f0 > 0 else 1.0
            q = row["offset_floor"]
            floor.setdefault(seg, np.zeros(3))[r] = q if q is not None and np.isfinite(q) else 0.0
            samples.setdefault(seg, np.zeros(3))[r] = row["n_samples"] or 0
        return cls(cov, sigma, ratio, floor, samples)

    def misfit_chi2(self, sid: int, r: int, coef: np.ndarray, n_used: int) -> tuple[float, int] | None:
        """(chi^2, degrees of freedom) of a segment's (C, A, B) misfit
        ``coef`` (output units), regressed on ``n_used`` of its samples,
        under its fit's covariance (scaled by the fit's samples over
        ``n_used`` where the diagnosis models fewer: a thinned capture);
        None where the fit has none. Where the fits measured a wander of the offsets (a
        floor, or a density near zero frequency above white), that wander
        is the C's scatter by construction (``fit.wander`` sizes the floor
        from it) and ``wander.against_wander`` tests their pattern: the
        sine terms (A, B) alone are tested."""
        cov = self.cov.get(sid)
        if cov is None or not np.all(np.isfinite(cov[r])):
            return None
        keep = slice(1, 3) if self.floor[sid][r] > 0 or self.ratio_zero[sid][r] > 1 else slice(0, 3)
        c = coef[keep]
        fitted = self.samples[sid][r] if sid in self.samples else 0
        thinned = max(1.0, fitted / n_used) if n_used > 0 else 1.0
        return float(c @ np.linalg.pinv(cov[r][keep, keep] * thinned) @ c), c.size

    def trend_variance(self, sid: int, r: int, s_tt: float, duration_s: float) -> float | None:
        """A least-squares trend's variance over a segment of ``duration_s``
        with sum of squared centred times ``s_tt``: the noise's within the
        segment, sigma^2 F(0) / S_tt, plus at most ``WANDER_SLOPE`` q^2 / T^2
        of a wander of the offsets' floor q; None where unknown."""
        sigma = self.sigma.get(sid)
        if sigma is None or not np.isfinite(sigma[r]) or sigma[r] <= 0 or s_tt <= 0:
            return None
        wander = WANDER_SLOPE * self.floor[sid][r] ** 2 / duration_s**2 if duration_s > 0 else 0.0
        return float(sigma[r] ** 2 * self.ratio_zero[sid][r] / s_tt + wander)


def segment_scan(res: Residuals, alpha: float, noise: SegmentNoise | None = None) -> list[Unexplained]:
    """Per segment and channel, what is left in a constant, the first
    harmonic and a linear trend: the segments disagreeing with the combined
    model (Geist 2017 section 3 consistency) or drifting within themselves,
    each against its fit's noise model (``noise``; white at the channel's
    level ``res.sigma`` where None or where a fit has none)."""
    out = []
    n_rates = len(np.unique(res.rate_hz))
    theta = np.deg2rad(res.theta_deg)
    first_harmonic = np.empty((theta.size, 3))  # every sample's, once, written in place
    first_harmonic[:, 0] = 1.0
    np.sin(theta, out=first_harmonic[:, 1])
    np.cos(theta, out=first_harmonic[:, 2])
    used = [_used_segments(res, r, lambda part: True) for r in range(3)]
    for kind in ("inconsistent", "trend"):
        stats = []  # (chi2, dof, segment id, slice, channel, coefficient of interest in output units)
        shared = None  # the Gram matrices of the channels that use every sample (the same rows)
        for r in range(3):
            rows, starts, segs = used[r]
            if not segs:
                continue
            e = res.resid[rows, r] / res.sigma[r]
            whole = rows.size == theta.size
            if kind == "inconsistent":
                basis = first_harmonic if whole else first_harmonic[rows]
            else:
                t = res.t_s[rows]
                mean_t = np.add.reduceat(t, starts) / np.diff(np.r_[starts, t.size])
                basis = (t - np.repeat(mean_t, np.diff(np.r_[starts, t.size])))[:, None]
            grams = _segment_grams(basis, starts) if not whole else shared
            if grams is None:
                grams = shared = _segment_grams(basis, starts)
            x2, coef = _segment_chi2(e, basis, starts, grams)
            for k, (sid, part) in enumerate(segs):
                size = coef[k] * res.sigma[r]
                tested: tuple[float, int] | None = None
                if noise is not None and kind == "inconsistent":
                    end = starts[k + 1] if k + 1 < starts.size else rows.size
                    tested = noise.misfit_chi2(sid, r, size, int(end - starts[k]))
                elif noise is not None:
                    t_seg = res.t_s[rows[starts[k]:starts[k + 1] if k + 1 < starts.size else rows.size]]
                    var = noise.trend_variance(sid, r, float(grams[k, 0, 0]), float(t_seg[-1] - t_seg[0]))
                    tested = None if var is None else (float(size[0] ** 2 / var), 1)
                stats.append((float(x2[k]), basis.shape[1], sid, part, r, size) if tested is None
                             else (tested[0], tested[1], sid, part, r, size))
        if not stats:
            continue
        total = sum(st[0] for st in stats)
        # the combined model's parameters per rate and channel: its responsivities (3), and its offset where
        # any segment's C was tested
        taken = sum(n_rates * (3 + any(st[1] == 3 for st in stats if st[4] == r)) for r in range(3))
        dof = sum(st[1] for st in stats) - (taken if kind == "inconsistent" else 0)
        p = min(1.0, chi2_sf(total, max(dof, 1)) * 2)
        if p >= alpha:
            continue
        _, _, sid, part, r, size = max(stats, key=lambda st: st[0])
        reduction = np.zeros(3)
        for st in stats:
            reduction[st[4]] += st[0] * res.sigma[st[4]] ** 2
        what = ("a constant or first-harmonic misfit" if kind == "inconsistent"
                else f"a trend of {size[0]:.2g} {res.output_unit} per s")
        out.append(Unexplained(
            kind, f"segment {sid} ({_describe(res, part)}), channel {CHANNELS[r]} most",
            f"segments depart from the combined model by {what} beyond the measured noise (largest: "
            f"{np.abs(size).max():.2g} {res.output_unit} in segment {sid}, channel {CHANNELS[r]}; chi-square {total:.0f} "
            f"on {dof}; {p_is(p)})",
            p, reduction, dof,
        ))
    return out


def residual_autoregression(res: Residuals, max_order: int = MAX_AR_ORDER) -> list[np.ndarray]:
    """Per channel, the coefficients a_1..a_p of the autoregression
    x_t = sum a_k x_t-k + e_t that describes the residuals (each segment's
    taken about its mean: a wander slower than a segment is the offsets'
    floor), by least squares on the samples with ``max_order`` consecutive
    predecessors in their run (``Observations.run``) (the covariance method: Yule-Walker's
    tapering biases a filter's steep spectrum, Percival & Walden 1993
    section 9.7), of the order 0..``max_order`` with the least
    AIC = N log v_p + 2 p (v_p the innovations' mean square)."""
    out = []
    for r in range(3):
        rows, starts, segs = _used_segments(res, r, lambda part: True)
        if not segs:
            out.append(np.zeros(0))
            continue
        x = res.resid[rows, r].astype(float)
        counts = np.diff(np.r_[starts, rows.size])
        x -= np.repeat(np.add.reduceat(x, starts) / counts, counts)
        seg_of = np.repeat(np.arange(starts.size), counts)
        # the samples whose max_order predecessors are the samples before, in their run
        t = np.arange(max_order, x.size)
        run = seg_of if res.run is None else res.run[rows]   # predecessors in time, not across a gap
        ok = (run[t] == run[t - max_order]) & (rows[t] - rows[t - max_order] == max_order)
        t = t[ok]
        if t.size < 10 * (max_order + 1):
            out.append(np.zeros(0))
            continue
        lagged = np.stack([x[t - k] for k in range(1, max_order + 1)], axis=1)
        best, _ = akaike_autoregression(x[t], lagged)
        out.append(best)
    return out


def _innovations(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """Rows of ``x`` (steps, n) filtered by 1 - sum a_k L^k, the first p samples dropped."""
    p = a.size
    e = x[:, p:].copy()
    for k in range(1, p + 1):
        e -= a[k - 1] * x[:, p - k:x.shape[1] - k]
    return e


def static_step_scan(res: Residuals, step_id: np.ndarray, alpha: float,
                     autoregression: list[np.ndarray] | None = None) -> list[Unexplained]:
    """Geist 2017 Appendix B on the static steps' samples before averaging:
    no correlation and normality, beyond the recording's noise model (the
    ``autoregression`` per channel of ``residual_autoregression``; white
    where None). Each step's samples are taken about their own mean,
    prewhitened, and pooled over steps (a common noise is the model's
    premise), so the tests are those of one large sample: the lag-1
    autocorrelation (E = -1/n for a demeaned step of n samples, variance
    1/N) and the D'Agostino-Pearson K^2 test. Combining per-step p-values
    instead (Fisher) is anti-conservative: K^2 is not calibrated at 50
    samples."""
    out = []
    static = ~res.rotating & (step_id >= 0)
    _, first, size = np.unique(step_id[static], return_index=True, return_counts=True)
    rows = np.flatnonzero(static)
    for r, channel in enumerate(CHANNELS):
        a = np.zeros(0) if autoregression is None else autoregression[r]
        pooled, lag_sum, ss_sum, bias = [], 0.0, 0.0, 0.0
        for n in np.unique(size[size >= 20 + a.size]):
            idx = rows[first[size == n]][:, None] + np.arange(n)[None, :]
            ok = res.use[idx, r].all(axis=1)
            x = res.resid[idx[ok], r]
            x = _innovations(x - x.mean(axis=1, keepdims=True), a)
            x = x - x.mean(axis=1, keepdims=True)
            m = x.shape[1]
            pooled.append(x.ravel())
            lag_sum += float(np.sum(x[:, 1:] * x[:, :-1]))
            ss_sum += float(np.sum(x * x))
            bias += x.shape[0] * m * (-1.0 / m)
        if not pooled:
            continue
        values = np.concatenate(pooled)
        if values.size < 200 or ss_sum == 0:
            continue
        r1 = lag_sum / ss_sum
        z = (r1 - bias / values.size) * np.sqrt(values.size)
        model = "" if a.size == 0 else f" after the noise's autoregression of order {a.size}"
        for kind, p, what in (
            ("correlated", 2 * float(ndtr(-abs(z))), f"lag-1 autocorrelation {r1 + 0.0:.3f}{model} (z = {z:.1f})"),
            ("non_normal", normal_p(values), f"non-normal scatter{model}"),
        ):
            p_family = min(1.0, p * 6)
            if p_family < alpha:
                out.append(Unexplained(
                    kind, f"static steps, channel {channel}",
                    f"static-step samples of channel {channel} show {what} (Geist 2017 Appendix B; {values.size} "
                    f"samples of {int(np.sum(size >= 20 + a.size))} steps, {p_is(p_family)})", p_family, np.zeros(3), 0,
                ))
    return out
