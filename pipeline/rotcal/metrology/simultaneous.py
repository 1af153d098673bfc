"""Simultaneous solution: Geist 2017 section 3, first alternative. All
segments of one rate are fitted at once to the samples, with the
responsivity components shared (Eq. 9 without its subscripts 1 and 2, so
r_s1 = r_s2) and one offset per segment and channel (Geist's O_rs),

    R_r = O_rk - (g r)_a sin(theta) + (g r)_b cos(theta),

(a, b) = (y, z), (x, z), (x, y) for a segment about x, y, z
(docs/conventions.md; Eq. 9 with the signs of Eq. 5). Segments fitted with the
four-parameter sine fit keep their rate as a parameter here too
(theta = theta_0 + kappa_k (theta_cmd - theta_0)), so its uncertainty is
carried.

The fit is generalised least squares on the samples in two stages
(feasible GLS): ordinary least squares first, then each segment's samples
weighted by the inverse of its channels' residual covariance Sigma_k from
the first stage (held fixed, so that a model that does not fit cannot make
the weights chase the residuals). Its covariance is N^-1 (N the normal
matrix); since N is a sum over the independent segments, N^-1 N_k N^-1 is
each segment's contribution, which gives the budget. When the model is
wrong (a rate error fitted with the commanded rate, say) the two solutions
weight the misfit differently and disagree far beyond their uncertainties:
a finding, as in the consistency checks. The offset O_r is the inverse-variance weighted mean of
the O_rk (Eq. 12), with the full covariance propagated.

This is an independent route to the intrinsic parameters (it reads the
samples, not the per-segment fits): it must agree with the per-segment
solution of ``combine`` within the uncertainties.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.labelled import STATE, segment_input, units
from rotcal.fit.normal import SineSums
from rotcal.fit.segments import segment_rows
from rotcal.fit.sinemodel import basis, normal_from, precision_from, residuals, solve
from rotcal.model.physics import CHANNELS, COS_COMPONENT, INTRINSIC, SIN_COMPONENT, axis_index
from rotcal.model.results import Failure, IntrinsicResult
from rotcal.tables import conform, schema

MAX_ITERATIONS = 30


@dataclass(frozen=True, eq=False)
class SegmentSamples:
    """One fitted segment's samples: table angle (degrees), outputs (one
    array per channel, views of the sample table: no copy held), and the
    rate scale kappa to start from (None: the angle is trusted)."""

    segment: int
    axis: str
    theta_deg: np.ndarray
    channels: tuple[np.ndarray, ...]
    kappa: float | None

    @property
    def n(self) -> int:
        return self.theta_deg.size

    @property
    def y(self) -> np.ndarray:
        """The outputs (n, 3), built when wanted, in ``DataFrame.to_numpy``'s layout."""
        y = np.empty((self.theta_deg.size, len(self.channels)), order="F")
        for r, column in enumerate(self.channels):
            y[:, r] = column
        return y

    def sums(self, coef: np.ndarray, beta: np.ndarray, kappa_index: int | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Z^T Z, Z^T e, e^T e and the largest |y| at the channels'
        coefficients ``coef`` (3, 5), e the residuals (``sinemodel``)."""
        theta_unw = np.unwrap(self.theta_deg, period=360.0)
        psi = np.deg2rad(theta_unw - theta_unw[0])
        theta = np.deg2rad(theta_unw[0]) + beta[kappa_index] * psi if kappa_index is not None else np.deg2rad(self.theta_deg)
        z = basis(theta, psi)
        y = self.y
        resid = residuals(z, y, coef)
        return (np.einsum("ni,nj->ij", z, z), np.einsum("ni,nb->ib", z, resid), np.einsum("na,nb->ab", resid, resid),
                float(np.max(np.abs(y))))


@dataclass(frozen=True, eq=False)
class SegmentSums:
    """One three-parameter segment as the sums a streamed run accumulates
    (``fit.normal``): Z^T Z and Z^T Y of the basis (1, sin theta, cos theta),
    the segment's own fit (coefficients C_0, channel x basis) with its
    residual products R_0^T R_0, and the largest |y|. At other coefficients
    C the residuals are R = R_0 - Z (C - C_0)^T, so

        Z^T R = Z^T Y - Z^T Z C^T,
        R^T R = R_0^T R_0 - R_0^T Z D^T - D Z^T R_0 + D Z^T Z D^T,  D = C - C_0,

    exact, and without the cancellation Y^T Y - ... would suffer (R_0 is
    the noise, Y the signal)."""

    segment: int
    axis: str
    n: int
    gram: np.ndarray   # (3, 3)
    zty: np.ndarray    # (3 basis, 3 channels)
    coef: np.ndarray   # (3 channels, 3 basis): the segment's own fit
    rtr: np.ndarray    # (3, 3) at ``coef``
    y_max: float
    kappa: None = None  # the commanded rate is trusted (three-parameter fits only)

    @classmethod
    def of_fit(cls, segment: int, axis: str, n: int, fit: SineSums) -> SegmentSums:
        """The sums a segment's three-parameter fit left (``fit.segments``): an
        in-memory run's, the same as a streamed run accumulates."""
        return cls(segment, axis, n, fit.gram, fit.xty.T.copy(), fit.coef, fit.rtr, fit.y_max)

    def sums(self, coef: np.ndarray, beta: np.ndarray, kappa_index: int | None
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """As ``SegmentSamples.sums``, on the basis's first three functions."""
        d = coef[:, :3] - self.coef
        ze0 = self.zty - self.gram @ self.coef.T  # Z^T R_0: zero but for rounding
        rtr = self.rtr - ze0.T @ d.T - d @ ze0 + d @ self.gram @ d.T
        return self.gram, self.zty - self.gram @ coef[:, :3].T, rtr, self.y_max


def segment_samples(samples: pl.DataFrame, fits: pl.DataFrame, rate_hz: float, four_parameter: bool,
                    sums: Mapping[int, SineSums] | None = None) -> list[SegmentSamples | SegmentSums]:
    """The ok segments of one rate, in segment order (``_segments``)."""
    return _segments(samples, _ok_by_rate(fits).get(rate_hz, []), four_parameter, sums)


def _segments(samples: pl.DataFrame, ok: list[dict], four_parameter: bool,
              sums: Mapping[int, SineSums] | None) -> list[SegmentSamples | SegmentSums]:
    """The segments of the fits rows ``ok``: from the sums of their
    three-parameter fits where ``sums`` holds them (the same normal
    equations, without another pass over the samples), else with their samples."""
    sums = sums or {}
    rows, out = None, list[SegmentSamples | SegmentSums]()
    for row in ok:
        rotating = four_parameter and row["kind"] == "rotation"
        if not rotating and row["segment"] in sums:
            out.append(SegmentSums.of_fit(row["segment"], row["axis"], row["n_samples"], sums[row["segment"]]))
            continue
        rows = segment_rows(samples) if rows is None else rows
        part = samples.slice(*rows[row["segment"]])
        out.append(SegmentSamples(row["segment"], row["axis"], part["angle_deg"].to_numpy(),
                                  tuple(part[c].to_numpy() for c in CHANNELS),
                                  row["rate_fit_hz"] / row["rate_hz"] if rotating else None))
    return out


def _ok_by_rate(fits: pl.DataFrame) -> dict[float, list[dict]]:
    """The ok static and rotation fits, one row a segment in segment order,
    by rate; rates ordered by magnitude (rate 0, the static result, first)."""
    ok = (fits.filter((pl.col("status") == "ok") & pl.col("kind").is_in(["static", "rotation"]))
          .unique("segment", keep="first").sort("segment"))
    by_rate: dict[float, list[dict]] = {}
    for row in ok.iter_rows(named=True):
        by_rate.setdefault(row["rate_hz"], []).append(row)
    return {rate: by_rate[rate] for rate in sorted(by_rate, key=lambda r: (abs(r), r))}


def _segment_system(seg: SegmentSamples | SegmentSums, k: int, kappa_index: int | None, beta: np.ndarray, n_params: int,
                    weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, float]]:
    """One segment's normal equations at ``beta`` with the channel weight
    matrix ``weight`` (``sinemodel``), and its residual products R^T R with
    the largest |y|, from which the weight its residuals give is computed
    (``_precision``; returned so that no segment's residuals are kept)."""
    a = axis_index(seg.axis)
    coef, design = np.zeros((3, 5)), np.zeros((3, 5, n_params))
    for r in range(3):
        i_sin, i_cos, i_off = 3 * r + SIN_COMPONENT[a], 3 * r + COS_COMPONENT[a], 9 + 3 * k + r
        coef[r, :3] = beta[i_off], -beta[i_sin], beta[i_cos]
        design[r, 0, i_off], design[r, 1, i_sin], design[r, 2, i_cos] = 1.0, -1.0, 1.0
        if kappa_index is not None:  # dR/dkappa = -(rho_a cos + rho_b sin) psi
            design[r, 4, kappa_index], design[r, 3, kappa_index] = -beta[i_sin], -beta[i_cos]
    gram, ze, rtr, y_max = seg.sums(coef, beta, kappa_index)
    return (*normal_from(gram, ze, design[:, : gram.shape[0]], weight), (rtr, y_max))


def _precision(seg: SegmentSamples | SegmentSums, residual: tuple[np.ndarray, float]) -> np.ndarray:
    """The channel weight of a segment's residuals (``sinemodel.precision_from``); unit for noise-free data."""
    weight = precision_from(residual[0], seg.n, residual[1], 3)
    return np.eye(3) if weight is None else weight


def simultaneous_rate(rate_hz: float, segs: Sequence[SegmentSamples | SegmentSums], g_local: float, g_uncertainty: float,
                      noise: Mapping[int, np.ndarray] | None = None) -> IntrinsicResult | Failure:
    """The simultaneous least-squares solution of one rate (see module
    docstring); ``noise``: each segment's measured noise (``segment_noise``),
    which widens the covariance (``coloured``; none: white)."""
    measured = {3 * r + c for s in segs for r in range(3) for c in (SIN_COMPONENT[axis_index(s.axis)], COS_COMPONENT[axis_index(s.axis)])}
    missing = [STATE[i] for i in range(9) if i not in measured]
    if missing:
        axes = sorted({s.axis for s in segs}) or ["none"]
        return Failure(rate_hz, f"segments about axes {', '.join(axes)} leave {', '.join(missing)} unmeasured")
    n_seg = len(segs)
    kappa_index, p = [], 9 + 3 * n_seg
    for s in segs:
        kappa_index.append(p if s.kappa is not None else None)
        p += s.kappa is not None
    beta = np.zeros(p)
    for s, j in zip(segs, kappa_index):
        if j is not None:
            beta[j] = s.kappa
    # two stages (feasible GLS): ordinary least squares, then each segment weighted by the inverse of
    # its channels' residual covariance from the first stage, held fixed while the rates converge
    weights = [np.eye(3)] * n_seg
    # hand-written Gauss-Newton on the O(n)-sum normal equations of ``sinemodel``, not fit.lsq.nonlinear:
    # scipy's least_squares needs every sample's Jacobian row, 6 to 19 times slower (measured for
    # ``sinefit4``, whose system this is: 0.04 s against 0.7 s on 20,000 samples)
    for stage in range(2):
        for iteration in range(MAX_ITERATIONS):
            blocks = [_segment_system(s, k, j, beta, p, weights[k]) for k, (s, j) in enumerate(zip(segs, kappa_index))]
            normal, rhs = sum((b[0] for b in blocks), np.zeros((p, p))), sum((b[1] for b in blocks), np.zeros(p))
            step = np.zeros(p)
            # the very first step leaves the rate scales alone: with the components still zero they are not identified
            free = slice(0, 9 + 3 * n_seg) if stage == iteration == 0 else slice(None)
            step[free], cov = solve(normal[free, free], rhs[free])
            beta += step
            if iteration > 0 and step @ rhs < 1e-8:  # the step's chi^2 is negligible
                break
        else:
            return Failure(rate_hz, f"simultaneous fit did not converge in {MAX_ITERATIONS} iterations")
        weights = [_precision(s, b[2]) for s, b in zip(segs, blocks)] if stage == 0 else weights
    white = cov
    cov, shares = coloured(cov, [b[0] for b in blocks], segs, kappa_index, noise) if noise else (cov, None)
    transform = np.zeros((12, p))
    transform[:9, :9] = np.eye(9)
    var = np.diag(cov)
    for r in range(3):
        idx = [9 + 3 * k + r for k in range(n_seg)]
        w = 1.0 / np.maximum(var[idx], 1e-290)
        transform[9 + r, idx] = w / w.sum()
    state, state_cov = transform @ beta, transform @ cov @ transform.T
    parts = []
    for k, (s, (block, _, _)) in enumerate(zip(segs, blocks)):
        share = transform @ (white @ block @ white if shares is None else shares[k]) @ transform.T
        parts.append((segment_input(s.segment, s.axis, s.n - 3), share))
    return IntrinsicResult.from_state(rate_hz, state, state_cov, g_local, g_uncertainty, parts)


def simultaneous(samples: pl.DataFrame, fits: pl.DataFrame, g_local: float, g_uncertainty: float,
                 four_parameter: bool = False, sums: Mapping[int, SineSums] | None = None) -> list[IntrinsicResult | Failure]:
    """Every rate's simultaneous solution (rate 0, the static result, first);
    ``sums``: the three-parameter fits' sums by segment (``_segments``)."""
    noise = segment_noise(fits)
    return [simultaneous_rate(rate, _segments(samples, ok, four_parameter, sums), g_local, g_uncertainty, noise)
            for rate, ok in _ok_by_rate(fits).items()]


def simultaneous_from_sums(sums: Mapping[int, SegmentSums], fits: pl.DataFrame, g_local: float,
                           g_uncertainty: float) -> list[IntrinsicResult | Failure]:
    """``simultaneous`` of three-parameter segments from their sums (a streamed run's)."""
    noise = segment_noise(fits)
    return [simultaneous_rate(rate, [sums[row["segment"]] for row in ok], g_local, g_uncertainty, noise)
            for rate, ok in _ok_by_rate(fits).items()]


def segment_noise(fits: pl.DataFrame) -> dict[int, np.ndarray]:
    """Each ok segment's measured noise (``fit.spectrum``, ``fit.wander``)
    from the fits table: (density ratio at zero, at the sine terms'
    frequency, offset floor) x channels."""
    ok = fits.filter(pl.col("status") == "ok")
    rank = {c: i for i, c in enumerate(CHANNELS)}
    out: dict[int, np.ndarray] = {}
    for row in ok.select("segment", "channel", "noise_ratio_zero", "noise_ratio_rate", "offset_floor").iter_rows():
        noise = out.setdefault(row[0], np.array([[1.0] * 3, [1.0] * 3, [0.0] * 3]))
        noise[:, rank[row[1]]] = [v if v is not None and np.isfinite(v) else d for v, d in zip(row[2:], (1.0, 1.0, 0.0))]
    return out


def coloured(cov: np.ndarray, blocks: list[np.ndarray], segs: Sequence[SegmentSamples | SegmentSums],
             kappa_index: list[int | None], noise: Mapping[int, np.ndarray]) -> tuple[np.ndarray, list[np.ndarray]]:
    """The covariance N^-1 (sum_k S_k N_k S_k) N^-1 and each segment's part
    of it: segment k's normal matrix N_k with its parameters scaled by the
    square root of its noise density's ratio to white at their frequency
    (Grenander 1954: zero for its offsets, the rotation's for the shared
    components it measures and its rate), and its offset floor's variance
    added to its offsets."""
    parts = []
    for k, (s, block, j) in enumerate(zip(segs, blocks, kappa_index)):
        ratio = noise.get(s.segment, np.array([[1.0] * 3, [1.0] * 3, [0.0] * 3]))
        a = axis_index(s.axis)
        scale = np.ones(cov.shape[0])
        for r in range(3):
            scale[9 + 3 * k + r] = np.sqrt(ratio[0, r])
            scale[[3 * r + SIN_COMPONENT[a], 3 * r + COS_COMPONENT[a]]] = np.sqrt(ratio[1, r])
        if j is not None:
            scale[j] = np.sqrt(ratio[1].max())
        part = cov @ (scale[:, None] * block * scale[None, :]) @ cov
        part[9 + 3 * k + np.arange(3), 9 + 3 * k + np.arange(3)] += ratio[2] ** 2
        parts.append(part)
    return sum(parts, np.zeros_like(cov)), parts


def simultaneous_frame(sim: list[IntrinsicResult], per_segment: list[IntrinsicResult], dataset: str, output_unit: str) -> pl.DataFrame:
    """The ``simultaneous`` table: the simultaneous solution beside the
    per-segment one of ``intrinsic.parquet``, and their difference."""
    other = {res.rate_hz: res for res in per_segment}
    rows = []
    for res in sim:
        ref = other.get(res.rate_hz)
        for i, (name, unit) in enumerate(zip(INTRINSIC, units(output_unit))):
            ref_value = ref.value[i] if ref is not None else np.nan
            ref_u = ref.std_uncertainty[i] if ref is not None else np.nan
            diff = res.value[i] - ref_value
            rows.append({
                "dataset": dataset, "rate_hz": res.rate_hz, "parameter": name, "unit": unit,
                "value": res.value[i], "std_uncertainty": res.std_uncertainty[i],
                "per_segment_value": ref_value, "per_segment_std_uncertainty": ref_u,
                "difference": diff, "difference_over_u": diff / ref_u if ref_u > 0 else np.nan,
            })
    if not rows:
        return schema("simultaneous").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("simultaneous").polars_schema, strict=False), "simultaneous")
