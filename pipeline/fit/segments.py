"""Fit: per segment, the linear model of each channel against the table angle,

    R_r(theta) = C + A sin(theta) + B cos(theta),

which is Gaitan & Geist 2021 Eq. 17 with omega t replaced by the commanded
angle theta (docs/conventions.md) for constant rotation, and Geist 2017
Eqs. 6 to 9 (with the signs of Eq. 5) for a static step sequence: the same
regression on every sample of every step, which weights each step mean by
its sample count and pools the noise of all samples.

The three channels share one design matrix, so one set of normal equations
serves all three, and the residual covariance between channels gives the
full 9 x 9 covariance of a segment's coefficients:
Cov = Sigma (x) (X^T X)^-1 with Sigma the residual covariance matrix.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.config import FitConfig
from rotcal.fit.normal import NormalSums, ResidualSums, SineSums, coefficient_covariance
from rotcal.fit.sinefit4 import four_parameter_fit
from rotcal.model.physics import CHANNELS
from rotcal.parallel import cores
from rotcal.tables import conform, schema

PARAMS = ("C", "A", "B")


@dataclass(frozen=True, eq=False)
class SegmentFit:
    """All three channels of one segment: coefficients (channel x (C, A, B)),
    their 9 x 9 covariance (channel-major), and residual statistics.
    A failed fit carries its reason and no numbers."""

    segment: int
    status: str
    reason: str | None
    n_samples: int
    coef: np.ndarray
    cov: np.ndarray
    sigma: np.ndarray
    rms: np.ndarray
    max_abs: np.ndarray
    lag1: np.ndarray
    rate_fit_hz: float
    u_rate_fit_hz: float = 0.0
    sums: SineSums | None = None  # a three-parameter fit's sums, for the simultaneous solution

    @property
    def dof(self) -> int:
        return max(self.n_samples - 3, 0) if self.status == "ok" else 0

    @classmethod
    def failed(cls, segment: int, n_samples: int, reason: str, rate_hz: float) -> SegmentFit:
        nan3 = np.full(3, np.nan)
        return cls(segment, "failed", reason, n_samples, np.full((3, 3), np.nan), np.full((9, 9), np.nan),
                   nan3, nan3, nan3, nan3, rate_hz)


def design(theta_deg: np.ndarray) -> np.ndarray:
    """Columns 1, sin(theta), cos(theta) (Gaitan 2021 Eq. 17)."""
    theta = np.deg2rad(theta_deg)
    return np.column_stack([np.ones_like(theta), np.sin(theta), np.cos(theta)])


def linear_fit(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares of every column of ``y`` on ``x`` by normal equations.

    Returns (coef (k, p), cov (k p, k p) channel-major, residuals (n, k)).
    """
    xtx_inv = np.linalg.inv(x.T @ x)
    coef = (xtx_inv @ (x.T @ y)).T
    resid = y - x @ coef.T
    sigma2 = resid.T @ resid / max(x.shape[0] - x.shape[1], 1)
    return coef, np.kron(sigma2, xtx_inv), resid


def residual_stats(resid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """RMS, largest magnitude and lag-1 autocorrelation of each column."""
    ss = np.einsum("ij,ij->j", resid, resid)
    lag1 = np.einsum("ij,ij->j", resid[1:], resid[:-1]) / np.where(ss > 0, ss, 1.0)
    return np.sqrt(ss / resid.shape[0]), np.abs(resid).max(axis=0), lag1


def refusal(kind: str, angle_source: str, theta_deg: np.ndarray, config: FitConfig) -> str | None:
    """Why a segment cannot be fitted against the table angle, or None."""
    n = theta_deg.size
    if angle_source == "none" or n < config.min_samples:
        return refusal_from(kind, angle_source, n, 0, 0.0, config)
    steps = np.unique(theta_deg).size if kind == "static" else 0  # a sort: only where the step count matters
    return refusal_from(kind, angle_source, n, steps, arc_deg(theta_deg), config)


def refusal_from(kind: str, angle_source: str, n: int, steps: int, span: float, config: FitConfig) -> str | None:
    """``refusal`` from a segment's sample count, distinct static angles and arc (``arc_deg``)."""
    if angle_source == "none":
        if kind == "rotation":
            return ("no angle reference: a rotation segment without angle_deg or a table channel "
                    "cannot be fitted against the table angle (reduce it as an unlabelled recording)")
        return "static steps without angle_deg"
    if n < config.min_samples:
        return f"too short: {n} samples (at least {config.min_samples} needed)"
    if kind == "static" and steps < 3:
        return f"only {steps} static angle{'s' if steps != 1 else ''} (at least 3 needed)"
    if span < config.min_span_deg:
        return f"angle range {span:.1f} deg is below the {config.min_span_deg:g} deg needed to separate offset and sine terms"
    return None


def arc_deg(theta_deg: np.ndarray) -> float:
    """The arc the angles cover on the circle, not their unwrapped range: a
    rotation sampled at a multiple of its rate (aliased) repeats one angle,
    however many turns it makes. The smaller of the ranges of theta mod 360
    and of (theta + 180) mod 360, so an arc across 0 deg is measured whole."""
    low, high = arc_bounds(theta_deg)
    return arc_from(low, high)


def arc_from(low: np.ndarray, high: np.ndarray) -> float:
    """The arc from the bounds of ``arc_bounds`` (of one block, or the
    smallest lows and largest highs of several)."""
    return float(min(high[0] - low[0], high[1] - low[1]))


def arc_bounds(theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The smallest and largest of theta mod 360 and of (theta + 180) mod
    360, computed in place (one scratch array; ``np.mod`` takes eight times
    as long on the long rotations); bounds are additive across blocks."""
    r = theta_deg / 360.0
    np.floor(r, out=r)
    r *= -360.0
    r += theta_deg  # theta mod 360 (the division is exact at whole turns)
    first = (float(r.min()), float(r.max()))
    r -= 180.0
    r[r < 0.0] += 360.0  # (theta + 180) mod 360
    return np.array([first[0], float(r.min())]), np.array([first[1], float(r.max())])


def stuck_from(low: np.ndarray, high: np.ndarray) -> str | None:
    """Why a segment's samples cannot be fitted, from each channel's
    smallest and largest value: a channel that holds one value throughout
    (pinned at full scale, or dead) has no residual scatter, so its fit
    would claim zero uncertainty and outweigh every other segment in the
    combination."""
    for channel, lo, hi in zip(CHANNELS, low, high):
        if lo == hi:
            return f"channel {channel} holds {lo:g} in every sample (stuck or saturated): nothing to fit"
    return None


def fit_segment(segment: int, kind: str, rate_hz: float, angle_source: str, theta_deg: np.ndarray,
                y: np.ndarray, config: FitConfig) -> SegmentFit:
    """Fit one segment's three channels (``y``: samples x channels); a
    segment that cannot be fitted becomes a failed record with its reason."""
    return _fit_channels(segment, kind, rate_hz, angle_source, theta_deg, tuple(y.T), config)


def _fit_channels(segment: int, kind: str, rate_hz: float, angle_source: str, theta_deg: np.ndarray,
                  channels: tuple[np.ndarray, ...], config: FitConfig) -> SegmentFit:
    """The fit, or a failure row where it is not finite: ingest refuses
    non-finite and absurd values, and this second guard keeps any value that
    still overflows the fit from being reported "ok" with NaN coefficients."""
    return finite(_fit(segment, kind, rate_hz, angle_source, theta_deg, channels, config), rate_hz)


def finite(fit: SegmentFit, rate_hz: float) -> SegmentFit:
    """``fit``, or its failure row where an ok fit is not finite."""
    if fit.status == "ok" and not (np.isfinite(fit.coef).all() and np.isfinite(fit.cov).all()):
        return SegmentFit.failed(fit.segment, fit.n_samples, "the fit is not finite (an angle or sample value too large "
                                 "for the sine fit): nothing to fit", rate_hz)
    return fit


def _fit(segment: int, kind: str, rate_hz: float, angle_source: str, theta_deg: np.ndarray,
         channels: tuple[np.ndarray, ...], config: FitConfig) -> SegmentFit:
    reason = refusal(kind, angle_source, theta_deg, config)
    if reason is None:
        low, high = np.array([y.min() for y in channels]), np.array([y.max() for y in channels])
        reason = stuck_from(low, high)
    if reason is not None:
        return SegmentFit.failed(segment, theta_deg.size, reason, rate_hz)
    n = theta_deg.size
    normal, residual, xtx_inv = sine3_sums(theta_deg, channels)  # the four-parameter fit starts from its coefficients
    if kind == "rotation" and config.sine_fit == "four_parameter":
        y = np.column_stack(channels)
        four = four_parameter_fit(theta_deg, y, residual.coef)
        if four is None:
            return SegmentFit.failed(segment, n, "four-parameter sine fit did not converge to a rate within 5 % of the commanded one", rate_hz)
        rms, max_abs, lag1 = residual_stats(four.resid)
        sigma = np.sqrt(np.einsum("ij,ij->j", four.resid, four.resid) / (n - 3))
        return SegmentFit(segment, "ok", None, n, four.coef, four.cov, sigma, rms, max_abs, lag1,
                          rate_hz * four.scale, abs(rate_hz) * four.u_scale)
    rtr = residual.products()
    return sine3_result(segment, rate_hz, n, residual.coef, coefficient_covariance(rtr, xtx_inv, n), rtr,
                        residual.max_abs, residual.lag,
                        SineSums(normal.gram, normal.xty, residual.coef, rtr, float(np.max(np.abs(np.r_[low, high])))))


def sine3_result(segment: int, rate_hz: float, n: int, coef: np.ndarray, cov: np.ndarray, rtr: np.ndarray,
                 max_abs: np.ndarray, lag: np.ndarray, sums: SineSums | None = None) -> SegmentFit:
    """The fit record of the three-parameter fit (``sine3_fit``'s outputs, and the sums it came from)."""
    ss = np.diag(rtr).copy()
    lag1 = lag / np.where(ss > 0, ss, 1.0)
    return SegmentFit(segment, "ok", None, n, coef, cov, np.sqrt(ss / (n - 3)), np.sqrt(ss / n), max_abs, lag1, rate_hz,
                      sums=sums)


# Starting a thread pool costs about 0.5 ms, what one core takes to fit some
# 20,000 samples: below this many samples in all, threads cost more than they save.
THREADED_MIN_SAMPLES = 100_000


def segment_rows(samples: pl.DataFrame) -> dict[int, tuple[int, int]]:
    """(first row, row count) of every segment; a segment's samples are one
    contiguous run (segments are label runs in time order)."""
    runs = samples.select(pl.col("segment").rle()).unnest("segment")
    starts = np.cumsum(runs["len"].to_numpy()) - runs["len"].to_numpy()
    return {int(seg): (int(a), int(k)) for seg, a, k in zip(runs["value"], starts, runs["len"]) if seg is not None}


def fit_segments(samples: pl.DataFrame, segments: pl.DataFrame, config: FitConfig, workers: int = 0) -> list[SegmentFit]:
    """Fit every static and rotation segment, in parallel across segments
    (threads, where there are enough samples to pay for them) on
    ``parallel.cores(workers)`` cores.

    Each segment's columns are zero-copy slices of ``samples``, so the stage
    holds no copy of the sample table. Results come back in segment order
    whatever the number of workers.
    """
    todo = segments.filter(pl.col("kind").is_in(["static", "rotation"]))
    rows = segment_rows(samples)

    def job(row: dict) -> SegmentFit:
        part = samples.slice(*rows[row["segment"]])
        angle = part["angle_deg"]
        theta = (angle.fill_null(np.nan) if angle.null_count() else angle).to_numpy()
        channels = tuple(part[c].to_numpy() for c in CHANNELS)  # Float64 by the samples schema
        return _fit_channels(row["segment"], row["kind"], row["rate_hz"], row["angle_source"], theta, channels, config)

    todo_rows = list(todo.iter_rows(named=True))
    n_workers = min(cores(workers), max(len(todo_rows), 1))
    if n_workers == 1 or sum(rows[r["segment"]][1] for r in todo_rows) < THREADED_MIN_SAMPLES:
        return [job(row) for row in todo_rows]
    with ThreadPoolExecutor(n_workers) as pool:
        return list(pool.map(job, todo_rows))



def fits_frame(fits: list[SegmentFit], segments: pl.DataFrame, dataset: str) -> pl.DataFrame:
    """The ``fits`` table: one row per (segment, channel), built column by
    column from the fits' arrays stacked (a frame from per-row dicts cost
    more than the fits)."""
    if not fits:
        return schema("fits").empty()
    info = {r["segment"]: r for r in segments.select("segment", "kind", "axis", "rate_hz").iter_rows(named=True)}
    seg = [info[f.segment] for f in fits for _ in CHANNELS]
    coef = np.stack([f.coef for f in fits]).reshape(-1, 3)   # (fit, channel) rows of (C, A, B)
    cov = np.stack([f.cov for f in fits])
    u = np.sqrt(np.diagonal(cov, axis1=1, axis2=2)).reshape(-1, 3)
    # blocks[f, r, :, k, :]: the 3 x 3 covariance of channel r's (C, A, B) with channel k's
    blocks = cov.reshape(-1, 3, 3, 3, 3)
    per_channel = {name: np.array([getattr(f, name)[r] for f in fits for r in range(3)])
                   for name in ("sigma", "rms", "max_abs", "lag1")}
    per_fit = {name: [getattr(f, name) for f in fits for _ in CHANNELS]
               for name in ("segment", "status", "reason", "n_samples", "dof", "rate_fit_hz", "u_rate_fit_hz")}
    columns = {
        "dataset": [dataset] * coef.shape[0], "segment": per_fit["segment"], "kind": [r["kind"] for r in seg],
        "axis": [r["axis"] for r in seg], "rate_hz": [r["rate_hz"] for r in seg], "channel": list(CHANNELS) * len(fits),
        **{name: per_fit[name] for name in ("status", "reason", "n_samples", "dof")},
        **{p: coef[:, i] for i, p in enumerate(PARAMS)}, **{f"u_{p}": u[:, i] for i, p in enumerate(PARAMS)},
        **{f"cov_{c}": pl.Series(blocks[:, :, :, k, :].reshape(-1, 9)).cast(pl.List(pl.Float64))
           for k, c in enumerate(CHANNELS)},
        "rate_fit_hz": per_fit["rate_fit_hz"], "u_rate_fit_hz": per_fit["u_rate_fit_hz"], "sigma": per_channel["sigma"],
        "rms": per_channel["rms"], "max_abs_residual": per_channel["max_abs"], "lag1_autocorr": per_channel["lag1"],
    }
    return conform(pl.DataFrame(columns, schema_overrides=schema("fits").polars_schema, strict=False), "fits")

# --- The three-parameter fit, batched --------------------------------------
# Normal equations of all three channels in one pass over the samples, a
# second pass for the residual statistics; both walk blocks of
# BLOCK_SAMPLES contiguous samples, so every operation is a 1-D numpy call
# on data in the core's cache. (``run_dataset`` keeps BLAS on one thread;
# a threaded dot product here would compete with the segment workers.)

BLOCK_SAMPLES = 32768
PROGRESSION_TOLERANCE_DEG = 1e-9  # far below any table encoder's resolution
_TABLE_SIZE = 4096
_TABLE_STEP_DEG = 360.0 / _TABLE_SIZE  # 0.087890625, exact in binary
_TABLE_SIN = np.sin(2 * np.pi * np.arange(_TABLE_SIZE) / _TABLE_SIZE)
_TABLE_COS = np.cos(2 * np.pi * np.arange(_TABLE_SIZE) / _TABLE_SIZE)
_INNER = 64  # inner length of the two-level progression bases


def sincos_deg(theta_deg: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of angles in degrees, to a few ulp, by angle addition:
    theta = k h + d with h = 360/4096 deg and |d| <= h/2, so

        sin(theta) = sin(k h) cos(d) + cos(k h) sin(d),
        cos(theta) = cos(k h) cos(d) - sin(k h) sin(d),

    with sin(k h), cos(k h) from a 4096-entry table and sin(d), cos(d) from
    their Taylor series to d^7 and d^6 (|d| < 7.7e-4 rad: truncation below
    1e-28). ``theta - k h`` is exact, so large angles (many turns) lose
    nothing to range reduction.
    """
    k = np.rint(theta_deg * (1.0 / _TABLE_STEP_DEG))
    d = np.deg2rad(theta_deg - k * _TABLE_STEP_DEG)
    index = k.astype(np.int64) & (_TABLE_SIZE - 1)
    d2 = d * d
    sin_d = d * (1.0 - d2 / 6.0 * (1.0 - d2 / 20.0 * (1.0 - d2 / 42.0)))
    cos_d = 1.0 - d2 / 2.0 * (1.0 - d2 / 12.0 * (1.0 - d2 / 30.0))
    sin_k, cos_k = _TABLE_SIN[index], _TABLE_COS[index]
    return sin_k * cos_d + cos_k * sin_d, cos_k * cos_d - sin_k * sin_d


def _progression_bases(step_deg: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """sin and cos of i step for i < n, as sin((64 q + r) step) by angle
    addition of n/64 + 64 sines."""
    outer = np.deg2rad(_INNER * step_deg * np.arange(-(-n // _INNER)))[:, None]
    inner = np.deg2rad(step_deg * np.arange(_INNER))
    sin_a, cos_a, sin_b, cos_b = np.sin(outer), np.cos(outer), np.sin(inner), np.cos(inner)
    return (sin_a * cos_b + cos_a * sin_b).ravel()[:n], (cos_a * cos_b - sin_a * sin_b).ravel()[:n]


class _Sines:
    """sin and cos of a segment's angles block by block. Along a constant
    rotation sampled at a constant rate theta_i = theta_0 + i step, and a
    block starting at angle a gets sin(a + i step) = sin a cos(i step) +
    cos a sin(i step) from bases shared by all blocks; a block off the
    progression (by more than PROGRESSION_TOLERANCE_DEG) uses ``sincos_deg``."""

    def __init__(self, theta_deg: np.ndarray):
        n = theta_deg.size
        self.theta0 = float(theta_deg[0])
        self.step = (float(theta_deg[-1]) - self.theta0) / max(n - 1, 1)
        # the bases only where the first interval is the mean one (never for static steps)
        progression = self.step and n > _INNER and abs(theta_deg[1] - theta_deg[0] - self.step) <= PROGRESSION_TOLERANCE_DEG
        self.bases = _progression_bases(self.step, min(n, BLOCK_SAMPLES)) if progression else None
        self.offsets = self.step * np.arange(min(n, BLOCK_SAMPLES))

    def __call__(self, theta_deg: np.ndarray, start: int) -> tuple[np.ndarray, np.ndarray]:
        m = theta_deg.size
        if self.bases is not None:
            first = self.theta0 + self.step * start
            off = theta_deg - self.offsets[:m]
            off -= first
            if max(off.max(), -off.min()) <= PROGRESSION_TOLERANCE_DEG:
                sin_a, cos_a = math.sin(math.radians(first)), math.cos(math.radians(first))
                sin_b, cos_b = self.bases[0][:m], self.bases[1][:m]
                return sin_a * cos_b + cos_a * sin_b, cos_a * cos_b - sin_a * sin_b
        return sincos_deg(theta_deg)


def sine3_fit(theta_deg: np.ndarray, channels: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """Least squares of each channel on ``C + A sin(theta) + B cos(theta)``
    (Gaitan 2021 Eq. 17), all channels at once, by normal equations.

    Returns coef (channels x (C, A, B)), the channel-major covariance
    Sigma (x) (X^T X)^-1 with Sigma = R^T R / (n - 3), R^T R (channel x
    channel residual products), and each channel's largest residual
    magnitude and lag-1 residual product sum.
    """
    normal, residual, xtx_inv = sine3_sums(theta_deg, channels)
    rtr = residual.products()
    return residual.coef, coefficient_covariance(rtr, xtx_inv, theta_deg.size), rtr, residual.max_abs, residual.lag


def sine3_sums(theta_deg: np.ndarray, channels: tuple[np.ndarray, ...]) -> tuple[NormalSums, ResidualSums, np.ndarray]:
    """``sine3_fit``'s two passes: the normal sums, the residual sums at the
    solved coefficients, and (X^T X)^-1."""
    n = theta_deg.size
    sines = _Sines(theta_deg)
    spans = [(a, min(a + BLOCK_SAMPLES, n)) for a in range(0, n, BLOCK_SAMPLES)]
    normal, bases = NormalSums(len(channels)), []
    for a, b in spans:
        s, c = sines(theta_deg[a:b], a)
        normal.add(s, c, [y[a:b] for y in channels])
        bases.append((s, c))
    coef, xtx_inv = normal.solve()
    residual = ResidualSums(coef)
    for (a, b), (s, c) in zip(spans, bases):
        residual.add(s, c, [y[a:b] for y in channels])
    return normal, residual, xtx_inv
