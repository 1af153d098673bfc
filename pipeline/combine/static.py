"""Static calibration of a recording without table segments: hand-placed
poses (imu_tk, ArduPilot style), labelled poses (imucal's ``x_p``, ``x_a``,
...) or jig positions (``gx, gy, gz``).

Positions whose reference acceleration is known (labels, jig) are fitted
with ``poses.reference_fit``; otherwise the still intervals are found by
``stillness`` and fitted with ``multiposition.orientation_free``. Either
way the result is the static (rate 0) set of intrinsic parameters, and the
per-pose table holds the |a| check: |a| after the full correction, with
offsets and sensitivities alone, and under the fit to the other half of the
positions (a two-fold cross-check of every other position).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.multiposition import OrientationFreeFit, orientation_free, pose_arrays
from rotcal.combine.poses import CorrectedPoses, ReferenceFit, correct_poses, labelled_poses, reference_fit, still_poses
from rotcal.model.physics import AXES, CHANNELS
from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table
from rotcal.tables import conform

FRAMES = {"label": "pose", "jig": "jig", "stillness": "intrinsic"}


@dataclass(frozen=True, eq=False)
class StaticReduction(Reduction):
    """The static reduction of a recording (its one result, rate 0, and the
    ``poses`` table), with how it was fitted, the fit, the positions used
    (pose table with ``cov_mean``) and the per-pose check (schema
    ``poses``)."""

    method: str
    fit: ReferenceFit | OrientationFreeFit
    positions: pl.DataFrame
    check: pl.DataFrame

    @property
    def result(self) -> IntrinsicResult:
        return self.fit.result


def _fit(positions: pl.DataFrame, g_local: float, g_uncertainty: float) -> ReferenceFit | OrientationFreeFit | Failure:
    if positions["source"][0] == "stillness":
        return orientation_free(positions, g_local, g_uncertainty)
    return reference_fit(positions, g_local, g_uncertainty)


def _predict(fit: ReferenceFit | OrientationFreeFit, positions: pl.DataFrame) -> CorrectedPoses:
    """|a| of ``positions`` under ``fit``, the excess scatter per position
    included (a new position scatters as much as the fitted ones did)."""
    m, cov = pose_arrays(positions)
    if isinstance(fit, ReferenceFit):
        return correct_poses(fit.result, m, cov + fit.excess_cov[None])
    return correct_poses(fit.result, m, cov, fit.excess_std**2)


def reduce_static(samples: pl.DataFrame, segments: pl.DataFrame, dataset: str, g_local: float,
                  g_uncertainty: float, positions: pl.DataFrame | None = None) -> StaticReduction | Failure:
    """The static result of a recording whose samples carry no table labels,
    or of the pose table ``positions`` (``poses.summary_poses``: the
    recording given as pose summaries)."""
    if positions is None:
        positions = labelled_poses(samples, segments)
    single = positions.filter(pl.col("n_samples") < 2)
    if single.height:
        return Failure(0.0, f"{single.height} of the {positions.height} labelled poses have one sample each: a pose's "
                            "scatter needs two or more (one row per pose? give its mean, standard deviation and count "
                            "as pose summaries, docs/inputs.md)")
    if positions.height == 0:
        positions = still_poses(samples)
        if positions.height == 0:
            return Failure(0.0, "no still intervals found")
    fit = _fit(positions, g_local, g_uncertainty)
    if isinstance(fit, Failure):
        return fit
    m, cov = pose_arrays(positions)
    after = correct_poses(fit.result, m, cov)
    fold = (positions["pose"].to_numpy() % 2).astype(np.int32)
    held = np.full(positions.height, np.nan)
    held_u = np.full(positions.height, np.nan)
    for k in (0, 1):
        other = _fit(positions.filter(pl.Series(fold != k)), g_local, g_uncertainty)
        if not isinstance(other, Failure):
            pred = _predict(other, positions.filter(pl.Series(fold == k)))
            held[fold == k], held_u[fold == k] = pred.magnitude, pred.magnitude_u
    source = positions["source"][0]
    check = positions.select(
        pl.lit(dataset).alias("dataset"), "pose", "label", "source", "t_start_ns", "t_end_ns", "n_samples",
        "temperature_c", *(f"mean_{c}" for c in CHANNELS),
        *(pl.Series(f"u_mean_{c}", np.sqrt(cov[:, r, r])) for r, c in enumerate(CHANNELS)),
        *(pl.col(f"ref_{s}").fill_null(np.nan) for s in AXES),
    ).with_columns(
        *(pl.Series(f"a_{s}", after.acceleration[:, i]) for i, s in enumerate(AXES)),
        fit_frame=pl.lit(FRAMES[source]),
        norm_orthogonal_m_s2=after.magnitude_orthogonal, norm_m_s2=after.magnitude, u_norm_m_s2=after.magnitude_u,
        deviation_rel=after.magnitude / g_local - 1.0, fold=fold,
        norm_held_out_m_s2=held, u_norm_held_out_m_s2=held_u,
    )
    method = "orientation-free" if source == "stillness" else "reference"
    check = conform(check, "poses")
    return StaticReduction(FRAMES[source], (fit.result,), (), (Table("poses", check),), (), method, fit, positions, check)
