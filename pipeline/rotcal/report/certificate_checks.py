"""The certificate's checks, read from a run's published tables: the |a|
check (the corrected acceleration's magnitude against g_local, per segment,
dwell or pose) and the main contributions to each parameter's uncertainty.

|a| of a segment: its sine fit R(theta) = C + A sin(theta) + B cos(theta)
per channel (``fits.parquet``), corrected by its rate's calibration
a = P (R - O) (Geist 2017 Eq. 18), has |a|^2 = |P (C - O)|^2 + (|P A|^2 +
|P B|^2) / 2 averaged over a turn, gravity turning in the plane of the
rotation; its standard uncertainty carries the fit's coefficient
covariance to first order (GUM 5.1.2), P and O taken as exact. The
phase of the fit drops out, so segments fitted against their own phase
check as well as those fitted against the table angle."""

from __future__ import annotations

import math

import numpy as np
import polars as pl

from rotcal.model.calibration import Calibration, RateCalibration
from rotcal.model.physics import CHANNELS, INTRINSIC

PPM = 1e6
NORM_COLUMNS = {"kind": pl.String, "item": pl.String, "rate_hz": pl.Float64, "norm_m_s2": pl.Float64,
                "u_norm_m_s2": pl.Float64, "deviation_ppm": pl.Float64, "held_out_ppm": pl.Float64}


def rate_entry(cal: Calibration, rate_hz: float) -> RateCalibration | None:
    """The calibration of ``rate_hz``, None when the run has none for it."""
    return next((r for r in cal.rates if math.isclose(r.rate_hz, rate_hz, rel_tol=1e-9, abs_tol=1e-12)), None)


def _channel_major(fits: pl.DataFrame) -> tuple[pl.DataFrame, np.ndarray, np.ndarray]:
    """The segments whose three channel fits are ok (one row each), their
    coefficients (n, 3 channels, C A B) and the 9 x 9 channel-major
    covariance of (C_u, A_u, B_u, C_v, ...) per segment."""
    ok = fits.filter(pl.col("status") == "ok")
    complete = ok.group_by("segment").len().filter(pl.col("len") == len(CHANNELS))["segment"]
    ok = ok.filter(pl.col("segment").is_in(complete.implode())).sort("segment", "channel")
    segments = ok.unique("segment", keep="first", maintain_order=True).select("segment", "kind", "axis", "rate_hz")
    n = segments.height
    if n == 0:  # every fit failed (e.g. rotations refused for their jitter): nothing to stack
        return segments, np.zeros((0, 3, 3)), np.zeros((0, 9, 9))
    coef = ok.select("C", "A", "B").to_numpy().reshape(n, 3, 3)
    # row r's cov_c: 3 x 3 covariance of channel r's (C, A, B) with channel c's
    blocks = np.stack([np.stack(ok[f"cov_{c}"].to_list()).reshape(n, 3, 3, 3) for c in CHANNELS], axis=2)
    cov = blocks.transpose(0, 1, 3, 2, 4).reshape(n, 9, 9)
    return segments, coef, cov


def segment_norms(fits: pl.DataFrame, cal: Calibration) -> pl.DataFrame:
    """|a| of every segment with three ok channel fits and a calibration at its rate (module docstring)."""
    if fits.is_empty():
        return pl.DataFrame(schema=NORM_COLUMNS)
    segments, coef, cov = _channel_major(fits)
    entries = [rate_entry(cal, r) for r in segments["rate_hz"]]
    keep = np.array([e is not None for e in entries], bool)
    if not keep.any():
        return pl.DataFrame(schema=NORM_COLUMNS)
    P = np.stack([e.P_matrix for e in entries if e is not None])
    O = np.stack([e.O_vector for e in entries if e is not None])  # noqa: E741 (the papers name the offsets O)
    coef, cov, segments = coef[keep], cov[keep], segments.filter(pl.Series(keep))
    static = np.einsum("nij,nj->ni", P, coef[:, :, 0] - O)
    turning = np.einsum("nij,njk->nik", P, coef[:, :, 1:])  # columns P A, P B
    norm = np.sqrt((static**2).sum(1) + (turning**2).sum((1, 2)) / 2)
    # d|a|/d(C_r, A_r, B_r) = (P(C - O) . P[:, r], PA . P[:, r] / 2, PB . P[:, r] / 2) / |a|
    grad = np.concatenate([np.einsum("ni,nir->nr", static, P)[:, :, None],
                           np.einsum("nik,nir->nrk", turning, P) / 2], axis=2).reshape(-1, 9) / norm[:, None]
    u = np.sqrt(np.einsum("ni,nij,nj->n", grad, cov, grad))
    labels = [f"segment {s} ({k}, axis {a}{'' if r == 0 else f', {r:g} Hz'})"
              for s, k, a, r in segments.select("segment", "kind", "axis", "rate_hz").iter_rows()]
    return pl.DataFrame({"kind": "segment fit", "item": labels, "rate_hz": segments["rate_hz"], "norm_m_s2": norm,
                         "u_norm_m_s2": u, "deviation_ppm": (norm / cal.g_local - 1) * PPM, "held_out_ppm": None},
                        schema=NORM_COLUMNS)


def pose_norms(poses: pl.DataFrame, g_local: float) -> pl.DataFrame:
    """|a| of each static pose as ``poses.parquet`` has it, with the held-out check (two-fold)."""
    labels = [f"pose {p}" + (f" ({lab})" if lab else "") for p, lab in poses.select("pose", "label").iter_rows()]
    return pl.DataFrame({"kind": "pose", "item": labels, "rate_hz": 0.0, "norm_m_s2": poses["norm_m_s2"],
                         "u_norm_m_s2": poses["u_norm_m_s2"], "deviation_ppm": poses["deviation_rel"] * PPM,
                         "held_out_ppm": (poses["norm_held_out_m_s2"] / g_local - 1) * PPM}, schema=NORM_COLUMNS)


def dwell_norms(dwells: pl.DataFrame, cal: Calibration) -> pl.DataFrame:
    """|a| of each dwell after the orientation-free calibration (``dwells.parquet``), with the standard
    uncertainty of its mean's noise (``cov_mean``) through the DC calibration, a = P (m - O),
    d|a|/dm = P^T a / |a|, P and O taken as exact; none without a DC calibration."""
    part = dwells.filter(pl.col("g_magnitude").is_not_null())
    dc = rate_entry(cal, 0.0)
    u = None
    if dc is not None and part.height:
        a = (part.select("mean_u", "mean_v", "mean_w").to_numpy() - dc.O_vector) @ dc.P_matrix.T
        grad = a @ dc.P_matrix / np.linalg.norm(a, axis=1)[:, None]
        u = np.sqrt(np.einsum("ni,nij,nj->n", grad, np.stack(part["cov_mean"].to_list()).reshape(-1, 3, 3), grad))
    return pl.DataFrame({"kind": "dwell", "item": [f"dwell {d} (segment {s})" for d, s in part.select("dwell", "segment").iter_rows()],
                         "rate_hz": 0.0, "norm_m_s2": part["g_magnitude"], "u_norm_m_s2": u,
                         "deviation_ppm": (part["g_magnitude"] / cal.g_local - 1) * PPM, "held_out_ppm": None},
                        schema=NORM_COLUMNS)


def norm_check(tables: dict[str, pl.DataFrame], cal: Calibration) -> pl.DataFrame:
    """Every |a| the run's tables give: poses, dwells, segment fits."""
    parts = []
    if "poses" in tables:
        parts.append(pose_norms(tables["poses"], cal.g_local))
    if "dwells" in tables:
        parts.append(dwell_norms(tables["dwells"], cal))
    if "fits" in tables:
        parts.append(segment_norms(tables["fits"], cal))
    return pl.concat(parts) if parts else pl.DataFrame(schema=NORM_COLUMNS)


def norm_remark(check: pl.DataFrame, cal: Calibration, detected: tuple[str, ...], coverage: float = 3.0) -> str:
    """A sentence on the items whose |a| lies beyond ``coverage`` standard
    uncertainties of g_local, so that none is shown without a word: under a
    refined model the segment fits are those of the recorded samples, which
    still hold the effects the refined model corrects; otherwise such an item
    is a misfit to look at. Empty when every item is within."""
    beyond = check.filter((pl.col("u_norm_m_s2") > 0)
                          & ((pl.col("norm_m_s2") - cal.g_local).abs() > coverage * pl.col("u_norm_m_s2")))
    if beyond.is_empty():
        return ""
    worst = beyond.sort(pl.col("deviation_ppm").abs(), descending=True)
    shown = "; ".join(f"{item} at {dev:+.0f} ppm" for item, dev in worst.select("item", "deviation_ppm").head(3).iter_rows())
    more = f" and {beyond.height - 3} more" if beyond.height > 3 else ""
    count = f"{beyond.height} item{'s' if beyond.height > 1 else ''} lie{'s' if beyond.height == 1 else ''}"
    head = f"{count} beyond {coverage:g} standard uncertainties of g_local ({shown}{more})"
    refined = [r.model for r in cal.rates if r.model == "refined"]
    segment_fits = beyond.filter(pl.col("kind") == "segment fit").height
    if refined and segment_fits and detected:
        return (f"{head}: segment fits are fits of the recorded samples, which still hold what the refined model "
                f"corrects ({', '.join(detected)}): they show that effect, not an error of the calibration.")
    return f"{head}: more than the noise explains; the diagnosis (section 6) says what it found."


def norm_summary(check: pl.DataFrame) -> pl.DataFrame:
    """Per kind of item: how many, mean and RMS deviation and the largest |deviation| (ppm of g_local)."""
    return (check.group_by("kind", maintain_order=True)
            .agg(pl.len().alias("n"), pl.col("deviation_ppm").mean().alias("mean_ppm"),
                 (pl.col("deviation_ppm") ** 2).mean().sqrt().alias("rms_ppm"),
                 pl.col("deviation_ppm").abs().max().alias("max_abs_ppm")))


def main_contributions(budget: pl.DataFrame | None, cal: Calibration, top: int = 2) -> pl.DataFrame:
    """Per rate and parameter, the ``top`` largest input groups of the
    variance (GUM 5.1.3) with their fractions, and where they come from:
    ``uncertainty_budget`` (the baseline model's) for the rates whose
    recommended model is the baseline; otherwise the calibration itself,
    which separates g_local (a sensitivity s = |r| scales with 1/g_local, so
    g contributes s u(g)/g; angles and offsets do not depend on it) from the
    rest (the noise of the fits, Type A)."""
    baseline = [rc.rate_hz for rc in cal.rates if rc.model == "baseline"]
    tabled = (pl.DataFrame(schema={"rate_hz": pl.Float64, "parameter": pl.String, "input": pl.String,
                                   "fraction": pl.Float64}) if budget is None else
              budget.filter((pl.col("source") != "combined") & pl.col("rate_hz").is_in(baseline))
              .select("rate_hz", "parameter",
                      pl.when(pl.col("source") == "noise")
                      .then(pl.format("noise of segment {} (axis {})", pl.col("segment"), pl.col("axis")))
                      .otherwise(pl.col("source")).alias("input"), "fraction"))
    covered = set(tabled["rate_hz"].to_list())
    rows = []
    for rc in (rc for rc in cal.rates if rc.rate_hz not in covered):
        for q in rc.parameters:
            g_part = (q.value * cal.g_local_uncertainty / cal.g_local) ** 2 if q.name.startswith("s_") else 0.0
            total = q.std_uncertainty**2
            rows += [(rc.rate_hz, q.name, "g_local", g_part / total if total else 0.0),
                     (rc.rate_hz, q.name, "the rest (noise, Type A)", 1 - g_part / total if total else 0.0)]
    groups = pl.concat([tabled.with_columns(pl.lit("uncertainty_budget.parquet").alias("from")),
                        pl.DataFrame(rows, schema=tabled.schema, orient="row")
                        .with_columns(pl.lit("calibration.json").alias("from"))])
    order = {name: i for i, name in enumerate(INTRINSIC)}
    return (groups.sort("fraction", descending=True).group_by("rate_hz", "parameter", maintain_order=True)
            .agg(pl.col("input").filter(pl.col("fraction") > 0).head(top),
                 pl.col("fraction").filter(pl.col("fraction") > 0).head(top),
                 pl.col("fraction").filter(pl.col("input") == "g_local").sum().alias("g_local_fraction"),
                 pl.col("from").first())
            .with_columns(pl.col("parameter").replace_strict(order, return_dtype=pl.Int32).alias("order"))
            .sort("rate_hz", "order").drop("order"))
