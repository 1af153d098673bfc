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

from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import polars as pl

from rotcal.config import FitConfig
from rotcal.fit.correlated import noise_scales
from rotcal.fit.normal import SineSums, coefficient_covariance
from rotcal.fit.pooled import across_segments, record_noise
from rotcal.fit.quantization import rounding_repeats
from rotcal.fit.refusals import refusal, stuck_from
from rotcal.fit.sinefit4 import four_parameter_fit
from rotcal.fit.sines import sincos_deg, sine3_sums
from rotcal.fit.spectrum import Periodogram, periodogram
from rotcal.fit.wander import OffsetCovariance, RecordNoise
from rotcal.model.physics import CHANNELS
from rotcal.noise.residuals import split_at_pauses
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
    lag2: np.ndarray | None = None  # each channel's residual lag-2 autocorrelation (``fit.correlated``)
    # ``fit.spectrum``: the residuals' periodogram in bands; the density ratios applied (offset, sine
    # terms x channels), each channel's between-segment offset sd, and why that was not measured
    spectrum: Periodogram | None = None
    noise_ratio: np.ndarray | None = None
    offset_floor: np.ndarray | None = None
    noise_note: str | None = None
    # the offsets' covariance between any windows of the record (``fit.wander``), the same for every fit of a recording
    offsets: OffsetCovariance | None = None

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


def residual_stats(resid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """RMS, largest magnitude and lag-1 and lag-2 autocorrelations of each column."""
    ss = np.einsum("ij,ij->j", resid, resid)
    lag1, lag2 = (np.einsum("ij,ij->j", resid[k:], resid[:-k]) / np.where(ss > 0, ss, 1.0) for k in (1, 2))
    return np.sqrt(ss / resid.shape[0]), np.abs(resid).max(axis=0), lag1, lag2


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
        rms, max_abs, lag1, lag2 = residual_stats(four.resid)
        sigma = np.sqrt(np.einsum("ij,ij->j", four.resid, four.resid) / (n - 3))
        return SegmentFit(segment, "ok", None, n, four.coef, four.cov, sigma, rms, max_abs, lag1,
                          rate_hz * four.scale, abs(rate_hz) * four.u_scale, lag2=lag2)
    rtr = residual.products()
    return sine3_result(segment, rate_hz, n, residual.coef, coefficient_covariance(rtr, xtx_inv, n), rtr,
                        residual.max_abs, residual.lag, residual.lag2,
                        SineSums(normal.gram, normal.xty, residual.coef, rtr, float(np.max(np.abs(np.r_[low, high])))))


def sine3_result(segment: int, rate_hz: float, n: int, coef: np.ndarray, cov: np.ndarray, rtr: np.ndarray,
                 max_abs: np.ndarray, lag: np.ndarray, lag2: np.ndarray, sums: SineSums | None = None) -> SegmentFit:
    """The fit record of the three-parameter fit (``sine3_fit``'s outputs:
    the lag-1 and lag-2 product sums; and the sums it came from)."""
    ss = np.diag(rtr).copy()
    norm = np.where(ss > 0, ss, 1.0)
    return SegmentFit(segment, "ok", None, n, coef, cov, np.sqrt(ss / (n - 3)), np.sqrt(ss / n), max_abs, lag / norm,
                      rate_hz, sums=sums, lag2=lag2 / norm)


# Starting a thread pool costs about 0.5 ms, what one core takes to fit some
# 20,000 samples: below this many samples in all, threads cost more than they save.
THREADED_MIN_SAMPLES = 100_000


def widened(fit: SegmentFit, step_rad: float) -> SegmentFit:
    """``fit`` with its covariance and rate uncertainty widened for noise
    correlated from sample to sample (``fit.correlated``); ``step_rad`` the
    angle step per sample."""
    scales = noise_scales(fit.lag1, fit.lag2, fit.n_samples, step_rad) if fit.status == "ok" else None
    if scales is None:
        return fit
    return replace(fit, cov=fit.cov * np.outer(scales[0], scales[0]), u_rate_fit_hz=fit.u_rate_fit_hz * scales[1])


def angle_step(rate_hz: float, t_first_ns: int, t_last_ns: int, n: int) -> float:
    """The angle a rotation turns from one sample to the next, 2 pi rate dt (radians)."""
    return 2 * np.pi * rate_hz * (t_last_ns - t_first_ns) / 1e9 / max(n - 1, 1)


def segment_rows(samples: pl.DataFrame) -> dict[int, tuple[int, int]]:
    """(first row, row count) of every segment; a segment's samples are one
    contiguous run (segments are label runs in time order)."""
    runs = samples.select(pl.col("segment").rle()).unnest("segment")
    starts = np.cumsum(runs["len"].to_numpy()) - runs["len"].to_numpy()
    return {int(seg): (int(a), int(k)) for seg, a, k in zip(runs["value"], starts, runs["len"]) if seg is not None}


def fit_segments(samples: pl.DataFrame, segments: pl.DataFrame, config: FitConfig, workers: int = 0,
                 own_phase: Mapping[int, SegmentFit] | None = None, clock_factor: float = 1.0) -> list[SegmentFit]:
    """Fit every static and rotation segment, in parallel across segments
    (threads, where there are enough samples to pay for them) on
    ``parallel.cores(workers)`` cores.

    ``own_phase``: the fits, by segment, of rotation segments of
    ``segments`` already fitted against their own phase (``fit.sinefit``;
    the rate they were fitted at is their ``rate_fit_hz`` over
    ``clock_factor``, their phase from the segments' ``t_phase_ns``). They
    are not fitted again, but join what only all segments together measure
    (the noise's spectrum, the offsets' wander: ``fit.pooled``) in place of
    their own lag widening.

    Each segment's columns are zero-copy slices of ``samples``, so the stage
    holds no copy of the sample table. Results come back in the order of
    ``segments`` whatever the number of workers.
    """
    todo = segments.filter(pl.col("kind").is_in(["static", "rotation"]))
    rows = segment_rows(samples)
    own_phase = own_phase or {}

    def job(row: dict) -> SegmentFit:
        part = samples.slice(*rows[row["segment"]])
        if row["segment"] in own_phase:
            fit = own_phase[row["segment"]]
            return spectrum_of_own_phase(fit, part, fit.rate_fit_hz / clock_factor, row["t_phase_ns"])
        angle = part["angle_deg"]
        theta = (angle.fill_null(np.nan) if angle.null_count() else angle).to_numpy()
        channels = tuple(part[c].to_numpy() for c in CHANNELS)  # Float64 by the samples schema
        return segment_fit(row["segment"], row["kind"], row["rate_hz"], row["angle_source"], theta, channels,
                           int(part["t_ns"][0]), int(part["t_ns"][-1]), config)

    def residuals(fit: SegmentFit, row: dict) -> list[np.ndarray]:  # the noise model's pieces (``record_noise``)
        part = samples.slice(*rows[row["segment"]])
        y = np.column_stack([part[c].to_numpy() for c in CHANNELS])
        if row["segment"] in own_phase:
            theta = own_phase_angle(part["t_ns"].to_numpy(), fit.rate_fit_hz / clock_factor, row["t_phase_ns"])
        else:
            theta = fitted_angle(fit, part["angle_deg"].fill_null(np.nan).to_numpy(), row["rate_hz"])
        return split_at_pauses(part["t_ns"].to_numpy(), y - design(theta) @ fit.coef.T, dt)

    todo_rows = list(todo.iter_rows(named=True))
    n_workers = min(cores(workers), max(len(todo_rows), 1))
    if n_workers == 1 or sum(rows[r["segment"]][1] for r in todo_rows) < THREADED_MIN_SAMPLES:
        fits = [job(row) for row in todo_rows]
    else:
        with ThreadPoolExecutor(n_workers) as pool:
            fits = list(pool.map(job, todo_rows))
    t_ns = samples["t_ns"].to_numpy()
    first, last = (np.array([rows[r["segment"]][0] + k * (rows[r["segment"]][1] - 1) for r in todo_rows], np.int64) for k in (0, 1))
    t_first, t_last = (t_ns[i] / 1e9 if len(t_ns) else np.zeros(0) for i in (first, last))
    dt = float(np.median(np.diff(t_ns))) / 1e9 if len(t_ns) > 1 else 0.0
    record = (float(t_ns[0]) / 1e9, float(t_ns[-1]) / 1e9) if len(t_ns) else (0.0, 0.0)

    def noise_of(widened: list[SegmentFit]) -> RecordNoise | None:
        return record_noise([residuals(f, r) for f, r in zip(widened, todo_rows) if f.status == "ok"], dt, record) if dt > 0 else None
    return across_segments(fits, t_first, t_last, [(r["kind"], r["rate_hz"]) for r in todo_rows], [r["axis"] for r in todo_rows],
                           noise_of, modelled=dt > 0, record_start_s=record[0] if len(t_ns) else None)


def segment_fit(segment: int, kind: str, rate_hz: float, angle_source: str, theta_deg: np.ndarray,
                channels: tuple[np.ndarray, ...], t_first_ns: int, t_last_ns: int, config: FitConfig) -> SegmentFit:
    """One segment's fit from its own samples (angles, channels, first and
    last stamps), as every run fits it, in memory or block by block: the fit,
    widened where its rounding repeats (below the output step a sample's
    rounding follows its angle), with its residuals' periodogram."""
    fit = _fit_channels(segment, kind, rate_hz, angle_source, theta_deg, channels, config)
    fit = rounding_repeats(fit, theta_deg, channels)
    dt_s = (t_last_ns - t_first_ns) / 1e9 / max(theta_deg.size - 1, 1)
    return with_spectrum(fit, theta_deg, channels, rate_hz if kind == "rotation" else None, dt_s)


def own_phase_angle(t_ns: np.ndarray, rate_hz: float, t_phase_ns: int) -> np.ndarray:
    """The phase an own-phase fit's sine terms stand at (``fit.sinefit``), degrees."""
    return 360.0 * rate_hz * (t_ns - t_phase_ns) / 1e9


def spectrum_of_own_phase(fit: SegmentFit, part: pl.DataFrame, rate_hz: float, t_phase_ns: int) -> SegmentFit:
    """An own-phase fit (``fit.sinefit``: at ``rate_hz``, its phase from
    ``t_phase_ns``) of a segment's samples ``part`` with its residuals'
    periodogram, and without the widening for correlated noise it was given
    (``widened``), which the periodogram's density ratios replace
    (``fit.spectrum``), as for the segments fitted against the table angle."""
    if fit.status != "ok" or part.height < 2:
        return fit
    t_ns = part["t_ns"].to_numpy()
    scales = noise_scales(fit.lag1, fit.lag2, fit.n_samples, angle_step(rate_hz, int(t_ns[0]), int(t_ns[-1]), fit.n_samples))
    if scales is not None:
        fit = replace(fit, cov=fit.cov / np.outer(scales[0], scales[0]), u_rate_fit_hz=fit.u_rate_fit_hz / scales[1])
    dt_s = (t_ns[-1] - t_ns[0]) / 1e9 / max(t_ns.size - 1, 1)
    return with_spectrum(fit, own_phase_angle(t_ns, rate_hz, t_phase_ns), tuple(part[c].to_numpy() for c in CHANNELS),
                         fit.rate_fit_hz, dt_s)


def fitted_angle(fit: SegmentFit, theta_deg: np.ndarray, rate_hz: float) -> np.ndarray:
    """The angle the fit's sine terms stand at: a four-parameter fit's scaled rate applied to the table's."""
    kappa = fit.rate_fit_hz / rate_hz if rate_hz else 1.0
    if kappa == 1.0 or not np.isfinite(kappa):
        return theta_deg
    unwrapped = np.unwrap(theta_deg, period=360.0)
    return unwrapped[0] + kappa * (unwrapped - unwrapped[0])


def with_spectrum(fit: SegmentFit, theta_deg: np.ndarray, channels: tuple[np.ndarray, ...], rate_hz: float | None,
                  dt_s: float) -> SegmentFit:
    """``fit`` with its residuals' banded periodogram (``fit.spectrum``) at
    sample interval ``dt_s``: a rotation's of commanded ``rate_hz`` (None:
    a static sequence, its sine terms one cycle per segment)."""
    if fit.status != "ok" or not dt_s > 0:
        return fit
    kappa = fit.rate_fit_hz / rate_hz if rate_hz else 1.0  # a four-parameter fit's rate scale
    cycles = 1.0 if rate_hz is None else abs(rate_hz * kappa) * fit.n_samples * dt_s
    if kappa != 1.0:
        unwrapped = np.unwrap(theta_deg, period=360.0)
        theta_deg = unwrapped[0] + kappa * (unwrapped - unwrapped[0])
    sin, cos = sincos_deg(theta_deg)
    # channel by channel into one array (the same operations as broadcasting the three at once, a third of
    # the temporaries: a long segment read block by block is held whole while it is fitted)
    resid = np.empty((sin.size, len(channels)))
    for r, y in enumerate(channels):
        resid[:, r] = y - (fit.coef[r, 0] + sin * fit.coef[r, 1] + cos * fit.coef[r, 2])
    del sin, cos
    return replace(fit, spectrum=periodogram(resid, dt_s, cycles))



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
        **noise_columns(fits),
    }
    return conform(pl.DataFrame(columns, schema_overrides=schema("fits").polars_schema, strict=False), "fits")


def noise_columns(fits: list[SegmentFit]) -> dict[str, object]:
    """The ``fits`` table's noise columns (``fit.spectrum``), one row per (fit, channel)."""
    ok = [f.status == "ok" for f in fits for _ in CHANNELS]
    ratio = np.concatenate([f.noise_ratio.T if f.noise_ratio is not None else np.ones((3, 2)) for f in fits])
    floor = np.concatenate([f.offset_floor if f.offset_floor is not None else np.zeros(3) for f in fits])
    return {"noise_ratio_zero": np.where(ok, ratio[:, 0], np.nan), "noise_ratio_rate": np.where(ok, ratio[:, 1], np.nan),
            "offset_floor": np.where(ok, floor, np.nan), "noise_note": [f.noise_note for f in fits for _ in CHANNELS]}
