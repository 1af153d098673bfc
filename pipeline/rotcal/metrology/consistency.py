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

from rotcal.combine.labelled import RateSegments, estimates_for, rate_segments
from rotcal.model.physics import AXES, CHANNELS
from rotcal.tables import conform, schema

FAMILY_ALPHA = 0.01


def chi2_sf(chi2: float, dof: int) -> float:
    """P(X >= chi2) for X ~ chi^2(dof)."""
    from scipy.special import chdtrc  # here, not at the top: scipy's import would slow every CLI start

    return float(chdtrc(dof, chi2))


def consistency_frame(fits: pl.DataFrame, g_local: float, dataset: str, output_unit: str, model: str,
                      by_rate: RateSegments | None = None) -> pl.DataFrame:
    """The ``consistency`` table of the segment ``fits`` under ``model``:
    one row per (rate, component or offset); ``by_rate``: ``rate_segments(fits)`` when the caller has it."""
    checks: list[tuple[float, int, list[str], np.ndarray, np.ndarray]] = []  # rate, target, axes, estimates, uncertainties
    for rate, segs in rate_segments(fits) if by_rate is None else by_rate:
        if not segs:
            continue
        coef = np.concatenate([s.coef for s in segs])
        var = np.concatenate([np.diag(s.cov) for s in segs])
        groups: dict[int, list] = {}
        for e in estimates_for(segs):
            groups.setdefault(e.target, []).append(e)
        for target in sorted(groups):
            est = groups[target]
            scale = 1.0 if target >= 9 else 1.0 / g_local
            x = np.array([e.sign * coef[e.index] for e in est]) * scale
            u = np.sqrt(np.array([var[e.index] for e in est])) * scale
            checks.append((rate, target, [e.axis for e in est], x, u))
    if not checks:
        return schema("consistency").empty()
    mean, u_mean, chi2, z = _statistics([c[3] for c in checks], [c[4] for c in checks])
    dof = np.array([c[3].size - 1 for c in checks])
    tested = (dof > 0) & np.isfinite(chi2)
    p_value = np.full(dof.size, np.nan)
    if tested.any():
        from scipy.special import chdtrc  # as chi2_sf, for every check at once

        p_value[tested] = chdtrc(dof[tested], chi2[tested])
    offset = [target >= 9 for _, target, *_ in checks]
    channel = [CHANNELS[t - 9] if o else CHANNELS[t // 3] for (_, t, *_), o in zip(checks, offset)]
    component = ["" if o else AXES[t % 3] for (_, t, *_), o in zip(checks, offset)]
    frame = pl.DataFrame({
        "dataset": [dataset] * len(checks), "rate_hz": [c[0] for c in checks],
        "quantity": [f"O_{ch}" if o else f"{ch}_{co}" for ch, co, o in zip(channel, component, offset)],
        "channel": channel, "component": component, "source_axes": [",".join(c[2]) for c in checks],
        "estimates": [c[3].tolist() for c in checks], "std_uncertainties": [c[4].tolist() for c in checks],
        "weighted_mean": mean, "std_uncertainty": u_mean, "z": z, "chi2": chi2, "dof": dof,
        "chi2_per_dof": np.divide(chi2, dof, out=np.full(dof.size, np.nan), where=dof > 0), "p_value": p_value,
        "unit": [output_unit if o else f"{output_unit}/(m/s^2)" for o in offset],
    }, schema_overrides=schema("consistency").polars_schema, strict=False)
    alpha = FAMILY_ALPHA / max(int(np.count_nonzero(dof > 0)), 1)
    frame = frame.with_columns(
        model=pl.lit(model), alpha=pl.lit(alpha),
        consistent=pl.when(pl.col("dof") > 0).then(pl.col("p_value") >= alpha).otherwise(None),
    )
    return conform(frame, "consistency")


def _statistics(x: list[np.ndarray], u: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per check (estimates ``x`` with uncertainties ``u``): the inverse-variance
    weighted mean, its uncertainty, chi^2 about it, and for two estimates
    z = (x_1 - x_2) / sqrt(u_1^2 + u_2^2). Noise-free estimates (no known
    uncertainty): their plain mean, and no statistic. Checks of one size
    are computed together, each row summed as its own array would be."""
    mean, u_mean, chi2, z = (np.full(len(x), np.nan) for _ in range(4))
    sizes = np.array([e.size for e in x])
    for k in np.unique(sizes).tolist():
        at = np.flatnonzero(sizes == k)
        xs, us = np.array([x[i] for i in at]).reshape(at.size, k), np.array([u[i] for i in at]).reshape(at.size, k)
        known = us > 0
        w = np.where(known, 1.0 / np.where(known, us, 1.0) ** 2, 0.0)
        total = w.sum(axis=1)
        weighted = total > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where(weighted, np.sum(w * xs, axis=1) / total, np.mean(xs, axis=1))
            mean[at], u_mean[at] = m, np.where(weighted, np.sqrt(1.0 / total), 0.0)
            chi2[at] = np.where(weighted, np.sum(w * (xs - m[:, None]) ** 2, axis=1), np.nan)
            if k == 2:
                spread = np.hypot(us[:, 0], us[:, 1])
                z[at] = np.where(spread > 0, (xs[:, 0] - xs[:, 1]) / spread, np.nan)
    return mean, u_mean, chi2, z


def consistency_note(frame: pl.DataFrame) -> str | None:
    """One line for the run's notes when some checks disagree, else None."""
    disagree = frame.filter(pl.col("consistent").not_()).height
    if not disagree:
        return None
    return (f"{disagree} of {frame.height} consistency checks (Geist 2017 section 3) disagree beyond their "
            "uncertainties: see consistency.parquet")
