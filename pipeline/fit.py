"""Fit: per segment, the linear model of each channel against the table angle,

    R_r(theta) = C + A sin(theta) + B cos(theta),

which is Gaitan & Geist 2021 Eq. 17 with omega t replaced by the commanded
angle theta (contract section 1) for constant rotation, and Geist 2017
Eqs. 6 to 9 (with the signs of Eq. 5) for a static step sequence: the same
regression on every sample of every step, which weights each step mean by
its sample count and pools the noise of all samples.

The three channels share one design matrix, so one set of normal equations
serves all three, and the residual covariance between channels gives the
full 9 x 9 covariance of a segment's coefficients:
Cov = Sigma (x) (X^T X)^-1 with Sigma the residual covariance matrix.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import polars as pl

from pipeline.config import FitConfig
from pipeline.physics import CHANNELS
from pipeline.sinefit4 import four_parameter_fit
from pipeline.tables import conform, schema

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

    @property
    def dof(self) -> int:
        return max(self.n_samples - 3, 0) if self.status == "ok" else 0

    @classmethod
    def failed(cls, segment: int, n_samples: int, reason: str, rate_hz: float) -> "SegmentFit":
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
    if angle_source == "none":
        if kind == "rotation":
            return ("no angle reference: a rotation segment without angle_deg or a table channel "
                    "cannot be fitted against the table angle (reduce it as an unlabelled recording)")
        return "static steps without angle_deg"
    if n < config.min_samples:
        return f"too short: {n} samples (at least {config.min_samples} needed)"
    steps = np.unique(theta_deg).size
    if kind == "static" and steps < 3:
        return f"only {steps} static angle{'s' if steps != 1 else ''} (at least 3 needed)"
    span = float(np.ptp(theta_deg))
    if span < config.min_span_deg:
        return f"angle range {span:.1f} deg is below the {config.min_span_deg:g} deg needed to separate offset and sine terms"
    return None


def fit_segment(segment: int, kind: str, rate_hz: float, angle_source: str, theta_deg: np.ndarray,
                y: np.ndarray, config: FitConfig) -> SegmentFit:
    """Fit one segment's three channels; a segment that cannot be fitted
    becomes a failed record with its reason."""
    reason = refusal(kind, angle_source, theta_deg, config)
    if reason is not None:
        return SegmentFit.failed(segment, theta_deg.size, reason, rate_hz)
    coef, cov, resid = linear_fit(design(theta_deg), y)
    rate_fit_hz, u_rate_fit_hz = rate_hz, 0.0
    if kind == "rotation" and config.sine_fit == "four_parameter":
        four = four_parameter_fit(theta_deg, y, coef)
        if four is None:
            return SegmentFit.failed(segment, theta_deg.size, "four-parameter sine fit did not converge to a rate within 5 % of the commanded one", rate_hz)
        coef, cov, resid = four.coef, four.cov, four.resid
        rate_fit_hz, u_rate_fit_hz = rate_hz * four.scale, abs(rate_hz) * four.u_scale
    rms, max_abs, lag1 = residual_stats(resid)
    sigma = np.sqrt(np.einsum("ij,ij->j", resid, resid) / (theta_deg.size - 3))
    return SegmentFit(segment, "ok", None, theta_deg.size, coef, cov, sigma, rms, max_abs, lag1, rate_fit_hz, u_rate_fit_hz)


def _workers(requested: int) -> int:
    return requested if requested > 0 else (os.cpu_count() or 1)


def fit_segments(samples: pl.DataFrame, segments: pl.DataFrame, config: FitConfig, workers: int = 0) -> list[SegmentFit]:
    """Fit every static and rotation segment, in parallel across segments.

    Samples of one segment are contiguous (segments are runs in time order).
    Results come back in segment order whatever the number of workers.
    """
    todo = segments.filter(pl.col("kind").is_in(["static", "rotation"]))
    seg_col = samples["segment"].to_numpy()
    theta_all = samples["angle_deg"].fill_null(np.nan).to_numpy()
    y_all = samples.select(CHANNELS).to_numpy()
    jobs = []
    for row in todo.iter_rows(named=True):
        where = np.flatnonzero(seg_col == row["segment"])
        part = slice(where[0], where[-1] + 1)
        jobs.append((row["segment"], row["kind"], row["rate_hz"], row["angle_source"], theta_all[part], y_all[part], config))
    n_workers = min(_workers(workers), max(len(jobs), 1))
    if n_workers == 1:
        return [fit_segment(*job) for job in jobs]
    with ThreadPoolExecutor(n_workers) as pool:
        return list(pool.map(lambda job: fit_segment(*job), jobs))


def fits_frame(fits: list[SegmentFit], segments: pl.DataFrame, dataset: str) -> pl.DataFrame:
    """The ``fits`` table: one row per (segment, channel)."""
    info = {r["segment"]: r for r in segments.iter_rows(named=True)}
    rows = []
    for f in fits:
        seg = info[f.segment]
        for r, channel in enumerate(CHANNELS):
            block = f.cov[3 * r : 3 * r + 3]
            u = np.sqrt(np.diag(f.cov)[3 * r : 3 * r + 3])
            rows.append({
                "dataset": dataset, "segment": f.segment, "kind": seg["kind"], "axis": seg["axis"],
                "rate_hz": seg["rate_hz"], "channel": channel, "status": f.status, "reason": f.reason,
                "n_samples": f.n_samples, "dof": f.dof,
                **dict(zip(PARAMS, f.coef[r])), **{f"u_{p}": u[i] for i, p in enumerate(PARAMS)},
                **{f"cov_{c}": block[:, 3 * k : 3 * k + 3].ravel().tolist() for k, c in enumerate(CHANNELS)},
                "rate_fit_hz": f.rate_fit_hz, "u_rate_fit_hz": f.u_rate_fit_hz, "sigma": f.sigma[r], "rms": f.rms[r],
                "max_abs_residual": f.max_abs[r], "lag1_autocorr": f.lag1[r],
            })
    if not rows:
        return schema("fits").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("fits").polars_schema, strict=False), "fits")
