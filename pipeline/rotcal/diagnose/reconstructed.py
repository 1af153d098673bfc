"""Table angles reconstructed for rotation segments that have none.

A segment fitted against its own phase phi = 360 f (t - t_phase)
(``rotcal.fit.sinefit``) sees the table angle theta = sigma_k (theta_k +
phi), with theta_k and sigma_k = +-1 solved jointly with the intrinsic
parameters by the phase-free reduction (``rotcal.combine.phasefree``, whose
sign convention this follows). Written into the samples as ``angle_deg``,
with the segment's axis and rate, the segments enter the diagnosis as if
referenced; the model's rotation follows those angles, and its effects
move them at the signed fitted rate sigma_k f from the segment's first
sample (``model.physics.uniform_angle``).

What the reconstruction cannot give is an angle independent of the signals:
the fitted rate is the rate the samples show, so a rate error of the table
or the logger's clock is absorbed (docs/effects.md, "Which effects each
recording can show").
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import polars as pl

from rotcal.diagnose.fitting import ModelFit
from rotcal.diagnose.model import predict


def with_reconstructed_angles(samples: pl.DataFrame, segments: pl.DataFrame, phases: pl.DataFrame
                              ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """``samples`` with the reconstructed ``angle_deg``, the segment's
    ``axis`` and ``rate_hz`` for the segments of ``phases``
    (``rotcal.combine.unreferenced.segment_phases``), and ``phase_rate_hz``
    (the signed rate the model's rotation runs at: sigma_k f there, the
    commanded rate elsewhere); ``segments`` with those segments starting at
    their first sample, where the reconstructed rotation is anchored."""
    per = (phases.join(segments.select("segment", seg_axis="axis", seg_rate_hz="rate_hz"), on="segment", how="left")
           .select("segment", "seg_axis", "seg_rate_hz", "t_phase_ns",
                   theta_ref_deg=pl.col("sigma") * pl.col("theta_k_deg"),
                   signed_rate_hz=pl.col("sigma") * pl.col("phase_rate_hz")))
    joined = samples.join(per, on="segment", how="left", maintain_order="left")
    here = pl.col("signed_rate_hz").is_not_null()
    elapsed_s = (pl.col("t_ns") - pl.col("t_phase_ns")).cast(pl.Float64) / 1e9
    out = joined.with_columns(
        angle_deg=pl.when(here).then(pl.col("theta_ref_deg") + 360.0 * pl.col("signed_rate_hz") * elapsed_s)
        .otherwise(pl.col("angle_deg")),
        axis=pl.when(here).then(pl.col("seg_axis")).otherwise(pl.col("axis")),
        rate_hz=pl.when(here).then(pl.col("seg_rate_hz")).otherwise(pl.col("rate_hz")),
        phase_rate_hz=pl.when(here).then(pl.col("signed_rate_hz")).otherwise(pl.col("rate_hz")),
    ).drop("seg_axis", "seg_rate_hz", "t_phase_ns", "theta_ref_deg", "signed_rate_hz")
    first = (samples.filter(pl.col("segment").is_in(phases["segment"].implode()))
             .group_by("segment").agg(first_ns=pl.col("t_ns").min()))
    anchored = (segments.join(first, on="segment", how="left", maintain_order="left")
                .with_columns(t_start_ns=pl.coalesce("first_ns", "t_start_ns")).drop("first_ns"))
    return out, anchored


def with_phases_free(fit: ModelFit, segments: np.ndarray, step_deg: float = 1e-3) -> ModelFit:
    """``fit`` whose normal matrix is the information left on its parameters
    when the reconstructed segments' phases are free as well (the Schur
    complement G - I_bt I_tt^-1 I_tb, Jacobian columns of the phases by
    central differences of the model): the phases come from the same
    samples, and held fixed they would leave their uncertainty out of every
    covariance (the cross-axis responsivities' by a fifth)."""
    obs, motion = fit.obs, fit.obs.motion
    columns = []
    for k in segments:
        on = obs.segment == k
        shifted = [predict(replace(obs, motion=replace(motion, theta_cmd_deg=np.where(on, motion.theta_cmd_deg + h, motion.theta_cmd_deg))),
                           fit.beta, fit.layout, fit.active, (None, None), fit.structure) for h in (step_deg, -step_deg)]
        columns.append((shifted[0] - shifted[1]) / (2 * np.radians(step_deg)))
    jac = np.stack(columns, axis=2)  # (n, 3, K): d output / d theta_k (per radian)
    p = fit.G.shape[0]
    cross = np.zeros((p, len(segments)))
    info = np.zeros((len(segments), len(segments)))
    for r, d in enumerate(fit.ev.designs):
        w = 1.0 / fit.sigma[r] ** 2
        e = d.rows_of(jac[:, r, :])
        info += w * e.T @ e
        cross[np.concatenate([d.base.ravel(), d.ext])] += w * d.transposed_times(e)
    return replace(fit, G=fit.G - cross @ np.linalg.solve(info, cross.T))
