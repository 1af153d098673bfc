"""Consistency: the checks of Geist 2017 section 3 before estimates are
averaged. Each responsivity component r_s is measured by two segments (r_s1,
r_s2 of Eq. 9) and each offset by three (O_rx, O_ry, O_rz); Eqs. 10 and 12
average them only "if [they] are consistent with the assumption that [they]
are samples drawn from the same random distribution".

rotcal tests that assumption for every quantity of every rate: the
estimates come from different segments, so they are independent, and under
it chi^2 = sum (x_k - x_bar)^2 / u_k^2 about their inverse-variance weighted
mean x_bar follows a chi^2 distribution with (number of estimates - 1)
degrees of freedom (the fits' residual dof are thousands, so the Type A
uncertainties are treated as known). For two estimates the signed
normalised difference z = (x_1 - x_2) / sqrt(u_1^2 + u_2^2) is given too
(z^2 = chi^2). The flag ``consistent`` uses a family-wise significance of 1 %
over all the dataset's checks (Bonferroni), so that a clean dataset raises a
false alarm in about 1 % of runs; the p-values let a reader choose another
level. Disagreement is a finding for the diagnosis (a centripetal offset, an
axis tilt or drift moves the offsets of one axis; a rate error or channel
delay moves components), never a reason to change the estimate.
"""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.combine.labelled import estimates_for, rate_segments
from rotcal.model.physics import AXES, CHANNELS
from rotcal.tables import conform, schema

FAMILY_ALPHA = 0.01


def chi2_sf(chi2: float, dof: int) -> float:
    """P(X >= chi2) for X ~ chi^2(dof)."""
    from scipy.special import chdtrc  # here, not at the top: scipy's import would slow every CLI start

    return float(chdtrc(dof, chi2))


def consistency_frame(fits: pl.DataFrame, g_local: float, dataset: str, output_unit: str, model: str) -> pl.DataFrame:
    """The ``consistency`` table of the segment ``fits`` under ``model``:
    one row per (rate, component or offset)."""
    rows = []
    for rate, segs in rate_segments(fits):
        if not segs:
            continue
        coef = np.concatenate([s.coef for s in segs])
        var = np.concatenate([np.diag(s.cov) for s in segs])
        groups: dict[int, list] = {}
        for e in estimates_for(segs):
            groups.setdefault(e.target, []).append(e)
        for target in sorted(groups):
            est = groups[target]
            offset = target >= 9
            scale = 1.0 if offset else 1.0 / g_local
            x = np.array([e.sign * coef[e.index] for e in est]) * scale
            u = np.sqrt(np.array([var[e.index] for e in est])) * scale
            rows.append(_row(dataset, rate, target, [e.axis for e in est], x, u, output_unit))
    if not rows:
        return schema("consistency").empty()
    frame = pl.DataFrame(rows, schema_overrides=schema("consistency").polars_schema, strict=False)
    alpha = FAMILY_ALPHA / max(frame.filter(pl.col("dof") > 0).height, 1)
    frame = frame.with_columns(
        model=pl.lit(model), alpha=pl.lit(alpha),
        consistent=pl.when(pl.col("dof") > 0).then(pl.col("p_value") >= alpha).otherwise(None),
    )
    return conform(frame, "consistency")


def _row(dataset: str, rate_hz: float, target: int, axes: list[str], x: np.ndarray, u: np.ndarray, output_unit: str) -> dict:
    offset = target >= 9
    channel = CHANNELS[target - 9] if offset else CHANNELS[target // 3]
    component = "" if offset else AXES[target % 3]
    known = u > 0
    w = np.where(known, 1.0 / np.where(known, u, 1.0) ** 2, 0.0)
    if w.sum() > 0:
        mean, u_mean = float(np.sum(w * x) / w.sum()), float(np.sqrt(1.0 / w.sum()))
        chi2 = float(np.sum(w * (x - mean) ** 2))
    else:  # noise-free estimates: their plain mean, and no statistic
        mean, u_mean, chi2 = float(np.mean(x)), 0.0, np.nan
    dof = x.size - 1
    z = float((x[0] - x[1]) / np.hypot(u[0], u[1])) if x.size == 2 and np.hypot(u[0], u[1]) > 0 else np.nan
    p_value = chi2_sf(chi2, dof) if dof > 0 and np.isfinite(chi2) else np.nan
    return {
        "dataset": dataset, "rate_hz": rate_hz,
        "quantity": f"O_{channel}" if offset else f"{channel}_{component}",
        "channel": channel, "component": component, "source_axes": ",".join(axes),
        "estimates": x.tolist(), "std_uncertainties": u.tolist(),
        "weighted_mean": mean, "std_uncertainty": u_mean, "z": z, "chi2": chi2, "dof": dof,
        "chi2_per_dof": chi2 / dof if dof > 0 else np.nan, "p_value": p_value,
        "alpha": np.nan, "consistent": None,
        "unit": output_unit if offset else f"{output_unit}/(m/s^2)",
    }


def consistency_note(frame: pl.DataFrame) -> str | None:
    """One line for the run's notes when some checks disagree, else None."""
    disagree = frame.filter(pl.col("consistent").not_()).height
    if not disagree:
        return None
    return (f"{disagree} of {frame.height} consistency checks (Geist 2017 section 3) disagree beyond their "
            "uncertainties: see consistency.parquet")
