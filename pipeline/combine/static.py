"""Static calibration of a recording without table segments: hand-placed
poses (imu_tk, ArduPilot style), labelled poses (imucal's ``x_p``, ``x_a``,
...) or jig positions (``gx, gy, gz``).

Positions whose reference acceleration is known (labels, jig) are fitted
with ``poses.reference_fit``; otherwise the still intervals are found by
``stillness`` and fitted with ``multiposition.orientation_free``, both the
nine parameters and the six of orthogonal axes where the poses determine
them (``posemodels``: the choice, and the angles no pose determines). Either
way the result is the static (rate 0) set of intrinsic parameters, and the
per-pose table holds the |a| check: |a| after the full correction, with
offsets and sensitivities alone, and under the fit to the other half of the
positions (a two-fold cross-check of every other position). When no model is
determined the refusal still carries the pose table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np
import polars as pl

from rotcal.combine.multiposition import FULL, ORTHOGONAL, OrientationFreeFit, orientation_free, pose_arrays
from rotcal.combine.posemodels import advice, choose_model, determines
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
    ``poses``); ``model`` names the model of its result (``baseline``, or
    ``orthogonal`` when the poses do not determine the nine parameters),
    ``nested`` the other models fitted, ``notes`` the model choice and
    ``chosen`` the model it chooses and why (``posemodels.choose_model``). A
    refusal has no result, its failure, and the pose table (``fit`` None)."""

    method: str
    fit: ReferenceFit | OrientationFreeFit | None
    positions: pl.DataFrame
    check: pl.DataFrame
    model: str = "baseline"
    nested: tuple[tuple[str, IntrinsicResult], ...] = ()
    notes: tuple[str, ...] = ()
    chosen: tuple[str, str] = ("baseline", "")

    @property
    def result(self) -> IntrinsicResult:
        return self.results[0]


Fitter = Callable[[pl.DataFrame, float, float], ReferenceFit | OrientationFreeFit | Failure]


def _predict(fit: ReferenceFit | OrientationFreeFit, positions: pl.DataFrame) -> CorrectedPoses:
    """|a| of ``positions`` under ``fit``, the excess scatter per position
    included (a new position scatters as much as the fitted ones did)."""
    m, cov = pose_arrays(positions)
    if isinstance(fit, ReferenceFit):
        return correct_poses(fit.result, m, cov + fit.excess_cov[None])
    return correct_poses(fit.result, m, cov, fit.excess_std**2)


def _check(positions: pl.DataFrame, dataset: str, fitter: Fitter, fit: ReferenceFit | OrientationFreeFit | None,
           g_local: float, g_uncertainty: float) -> pl.DataFrame:
    """The ``poses`` table: every position with the |a| check under ``fit``
    and under the fits to each half (NaN where there is no fit), and the
    angles each pose determines under an orientation-free fit."""
    m, cov = pose_arrays(positions)
    n = positions.height
    after = correct_poses(fit.result, m, cov) if fit is not None else CorrectedPoses(*(np.full(s, np.nan) for s in ((n, 3), n, n, n)))
    fold = (positions["pose"].to_numpy() % 2).astype(np.int32)
    held = np.full(n, np.nan)
    held_u = np.full(n, np.nan)
    for k in (0, 1) if fit is not None else ():
        other = fitter(positions.filter(pl.Series(fold != k)), g_local, g_uncertainty)
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
        determines=pl.Series(determines(after.acceleration) if isinstance(fit, OrientationFreeFit) else [None] * n,
                             dtype=pl.String),
    )
    return conform(check, "poses")


def reduce_static(samples: pl.DataFrame, segments: pl.DataFrame, dataset: str, g_local: float,
                  g_uncertainty: float, positions: pl.DataFrame | None = None) -> StaticReduction | Failure:
    """The static result of a recording whose samples carry no table labels,
    or of the pose table ``positions`` (``poses.summary_poses``: the
    recording given as pose summaries): the most general model its
    positions determine, with the nested orthogonal model and the choice
    between them (``posemodels``) for poses of unknown orientation; a
    refusal with the pose table when not even the six parameters of
    orthogonal axes are determined."""
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
    source = positions["source"][0]
    frame = FRAMES[source]
    if source != "stillness":
        fit = reference_fit(positions, g_local, g_uncertainty)
        if isinstance(fit, Failure):
            check = _check(positions, dataset, reference_fit, None, g_local, g_uncertainty)
            return StaticReduction(frame, (), (fit,), (Table("poses", check),), (), "reference", None, positions, check)
        check = _check(positions, dataset, reference_fit, fit, g_local, g_uncertainty)
        return StaticReduction(frame, (fit.result,), (), (Table("poses", check),), (), "reference", fit, positions, check)
    choice = choose_model(positions, g_local, g_uncertainty)
    general, free, model = ((choice.full, FULL, "baseline") if not isinstance(choice.full, Failure)
                            else (choice.orthogonal, ORTHOGONAL, "orthogonal"))
    fitter: Fitter = partial(orientation_free, free=free)
    if isinstance(general, Failure):
        check = _check(positions, dataset, fitter, None, g_local, g_uncertainty)
        full = choice.full.reason if isinstance(choice.full, Failure) else ""
        refusal = Failure(0.0, f"orthogonal axes (six parameters): {general.reason}; nine parameters: {full}")
        return StaticReduction(frame, (), (refusal,), (Table("poses", check),), (), "orientation-free", None, positions, check)
    check = _check(positions, dataset, fitter, general, g_local, g_uncertainty)
    directions = check.select(f"a_{s}" for s in AXES).to_numpy()
    nested = (("orthogonal", choice.orthogonal.result),) if model == "baseline" and not isinstance(choice.orthogonal, Failure) else ()
    return StaticReduction(frame, (general.result,), (), (Table("poses", check),), tuple(advice(directions)),
                           "orientation-free", general, positions, check, model, nested, (choice.note,), (choice.chosen, choice.reason))
