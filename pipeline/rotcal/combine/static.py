"""Static calibration of a recording without table segments: hand-placed
poses (imu_tk, ArduPilot style), labelled poses (imucal's ``x_p``, ``x_a``,
...) or jig positions (``gx, gy, gz``).

Jig positions, whose reference acceleration is known, are fitted with
``poses.reference_fit`` (12 parameters) and its nested model of orthogonal
axes (``refmodels``). Labelled poses are placed by hand: their labels are
approximate directions (``placement``), so they are fitted as still
intervals are, with ``multiposition.orientation_free``, both the nine
parameters and the six of orthogonal axes where the poses determine them
(``posemodels``: the choice, and the angles no pose determines; six faces
determine the six), and each pose is checked against its label. Either
way the result is the static (rate 0) set of intrinsic parameters, and the
per-pose table holds the |a| check: |a| after the full correction, with
offsets and sensitivities alone, and under the fit to the other half of the
positions (a two-fold cross-check of every other position). When no model is
determined the refusal still carries the pose table.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial
from typing import TypeAlias, TypeVar

import numpy as np
import polars as pl

from rotcal.combine.channels import channel_fault
from rotcal.combine.datasheet import with_datasheet
from rotcal.combine.directions import reference_fault
from rotcal.combine.multiposition import ORTHOGONAL, OrientationFreeFit, orientation_free, pose_arrays
from rotcal.combine.placement import label_tilts, off_label
from rotcal.combine.posemodels import ModelChoice, advice, choose_model, determines, gravity_cone
from rotcal.combine.poses import (
    CorrectedPoses,
    OrthogonalReferenceFit,
    ReferenceFit,
    correct_poses,
    labelled_poses,
    reference_fit,
    references,
    sample_poses,
    scatterless_poses,
    still_poses,
    without_scatter,
)
from rotcal.combine.refmodels import choose_reference_model, orthogonal_reference_fit, reference_advice
from rotcal.fit.means import modelled_poses
from rotcal.model.physics import AXES, CHANNELS
from rotcal.model.placement import Placement
from rotcal.model.results import Failure, IntrinsicResult, Reduction, Table
from rotcal.noise.poses import PoseCovariance
from rotcal.tables import conform

FRAMES = {"label": "pose", "jig": "jig", "stillness": "intrinsic"}
FULL_PARAMETERS = {"reference": "12 parameters", "orientation-free": "nine parameters"}
ORTHOGONAL_PARAMETERS = {"reference": "nine parameters with the rotation", "orientation-free": "six parameters"}


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
    fit: StaticFit | None
    positions: pl.DataFrame
    check: pl.DataFrame
    model: str = "baseline"
    nested: tuple[tuple[str, IntrinsicResult], ...] = ()
    notes: tuple[str, ...] = ()
    chosen: tuple[str, str] = ("baseline", "")

    @property
    def result(self) -> IntrinsicResult:
        return self.results[0]


StaticFit: TypeAlias = ReferenceFit | OrthogonalReferenceFit | OrientationFreeFit
Fitter = Callable[[pl.DataFrame, float, float], StaticFit | Failure]


def _predict(fit: StaticFit, positions: pl.DataFrame) -> CorrectedPoses:
    """|a| of ``positions`` under ``fit``, the excess scatter per position
    included (a new position scatters as much as the fitted ones did)."""
    m, cov = pose_arrays(positions)
    if isinstance(fit, OrientationFreeFit):
        return correct_poses(fit.result, m, cov, fit.excess_std**2)
    return correct_poses(fit.result, m, cov + fit.excess_cov[None])


def _check(positions: pl.DataFrame, dataset: str, fitter: Fitter, fit: StaticFit | None,
           g_local: float, g_uncertainty: float, frame: str) -> pl.DataFrame:
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
    check = positions.select(
        pl.lit(dataset).alias("dataset"), "pose", "label", "source", "t_start_ns", "t_end_ns", "n_samples",
        "temperature_c", *(f"mean_{c}" for c in CHANNELS),
        *(pl.Series(f"u_mean_{c}", np.sqrt(cov[:, r, r])) for r, c in enumerate(CHANNELS)),
        *(pl.col(f"ref_{s}").fill_null(np.nan) for s in AXES),
    ).with_columns(
        *(pl.Series(f"a_{s}", after.acceleration[:, i]) for i, s in enumerate(AXES)),
        fit_frame=pl.lit(frame),
        norm_orthogonal_m_s2=after.magnitude_orthogonal, norm_m_s2=after.magnitude, u_norm_m_s2=after.magnitude_u,
        deviation_rel=after.magnitude / g_local - 1.0, fold=fold,
        norm_held_out_m_s2=held, u_norm_held_out_m_s2=held_u,
        determines=pl.Series(determines(after.acceleration) if isinstance(fit, OrientationFreeFit) else [None] * n,
                             dtype=pl.String),
        label_tilt_deg=np.nan,
    )
    return conform(check, "poses")


def reduce_static(samples: pl.DataFrame, segments: pl.DataFrame, dataset: str, g_local: float,
                  g_uncertainty: float, positions: pl.DataFrame | None = None,
                  placement: Placement = Placement()) -> StaticReduction | Failure:
    """The static result of a recording whose samples carry no table labels,
    or of the pose table ``positions`` (``poses.summary_poses``: the
    recording given as pose summaries): the most general model its
    positions determine, with the nested orthogonal model and the choice
    between them (``refmodels`` with known references, ``posemodels``
    without); a refusal with the pose table when not even the orthogonal
    model is determined, its reason the poses' narrow gravity cone when
    they have one. ``placement``: the labels' tolerance and the datasheet's
    cross-axis bound (the prior of angles the poses do not determine)."""
    if positions is None:
        positions = sample_poses(samples) if placement.pose_means else labelled_poses(samples, segments)
    single = positions.filter(pl.col("n_samples") < 2)
    if single.height and single.height == positions.height:  # one row per pose: means without scatter
        positions = scatterless_poses(positions)
    elif single.height:
        return Failure(0.0, f"{single.height} of the {positions.height} labelled poses have one sample each: a pose's "
                            "scatter needs two or more (one row per pose? give its mean, standard deviation and count "
                            "as pose summaries, docs/inputs.md)")
    unused = None
    if positions.height == 0:
        positions, unused = still_poses(samples, dataset=dataset)
        if positions.height == 0:
            return Failure(0.0, "no still intervals found" + (f" that the stillness detector accepts ({unused.height} "
                                                              "rejected: too short or too noisy)" if unused.height else ""))
    # (a jig's references are exact: a hand's labels are placed off them by ``placement``'s measure)
    fault = channel_fault(positions) or (reference_fault(positions) if positions["source"][0] == "jig" else None)
    if fault is not None:
        return Failure(0.0, fault)
    # poses of the samples: their means' covariance between poses from the noise model (``noise.poses``)
    positions, between = modelled_poses(samples, positions) if samples is not None and not single.height \
        else (positions, None)
    reduction = _reduced(positions, dataset, g_local, g_uncertainty, placement, between)
    if not isinstance(reduction, Failure) and reduction.results:
        reduction = _with_datasheet(reduction, placement)
    if unused is not None and unused.height and not isinstance(reduction, Failure):
        reduction = with_unused(reduction, unused, positions.height)
    if between is not None and between.note and not isinstance(reduction, Failure):
        reduction = replace(reduction, notes=reduction.notes + (between.note,))
    if isinstance(reduction, Failure) or not without_scatter(positions):
        return reduction
    return replace(reduction, notes=reduction.notes + (
        f"{positions.height} pose means without scatter: no pose noise is known, so the scatter is taken from the fit's "
        "residuals (its residual degrees of freedom, n - p, set the coverage factor)",))


def _with_datasheet(reduction: StaticReduction, placement: Placement) -> StaticReduction:
    """The reduction's results (its own and the nested models') joined to
    the datasheet's priors of ``[device]`` (``combine.datasheet``), with the
    note naming the parameters that rest on them."""
    result, note = with_datasheet(reduction.result, placement)
    if note is None:
        return reduction
    nested = tuple((name, with_datasheet(r, placement)[0]) for name, r in reduction.nested)
    return replace(reduction, results=(result,) + reduction.results[1:], nested=nested, notes=reduction.notes + (note,))


AnyReduction = TypeVar("AnyReduction", bound=Reduction)


def with_unused(reduction: AnyReduction, unused: pl.DataFrame, used: int) -> AnyReduction:
    """``reduction`` with the still intervals found and not used: the
    ``still_unused`` table and the console's count (in a refusal's reason
    too)."""
    kind = unused["reason"].str.split(":").list.first().alias("kind")  # the reason's first clause: its kind
    why = "; ".join(f"{n} {reason}" for reason, n in unused.group_by(kind, maintain_order=True).len().iter_rows())
    warning = (f"{unused.height} of the {used + unused.height} still intervals found are not used (still_unused.parquet "
               f"lists each with its reason): {why}")
    # a refusal is all the console shows: it carries the count too
    failures = reduction.failures if reduction.results else tuple(
        Failure(f.rate_hz, f"{f.reason} ({warning})") for f in reduction.failures)
    return replace(reduction, tables=reduction.tables + (Table("still_unused", unused),), failures=failures,
                   warnings=reduction.warnings + (warning,))


def _reduced(positions: pl.DataFrame, dataset: str, g_local: float, g_uncertainty: float,
             placement: Placement, between: PoseCovariance | None = None) -> StaticReduction | Failure:
    """``reduce_static`` of a pose table."""
    source = positions["source"][0]
    if source == "jig":
        prior = placement.misalignment_u
        return _chosen(positions, dataset, choose_reference_model(positions, g_local, g_uncertainty, prior, between), "reference",
                       {"baseline": reference_fit, "orthogonal": partial(orthogonal_reference_fit, misalignment_u=prior)},
                       g_local, g_uncertainty)
    # the raw means' directions: gravity's when the offsets are small beside g (the refusal's reason only)
    cone = gravity_cone(pose_arrays(positions)[0])
    choice = choose_model(positions, g_local, g_uncertainty, placement.misalignment_u, placement.stated_u, between)
    if cone is not None and isinstance(choice.full, Failure) and isinstance(choice.orthogonal, Failure):
        return _chosen(positions, dataset, Failure(0.0, cone), "orientation-free", {}, g_local, g_uncertainty)
    reduction = _chosen(positions, dataset, choice, "orientation-free",
                        {"baseline": orientation_free, "orthogonal": partial(orientation_free, free=ORTHOGONAL)},
                        g_local, g_uncertainty)
    return _placed(reduction, placement) if reduction.fit is not None else reduction


def _placed(reduction: StaticReduction, placement: Placement) -> StaticReduction:
    """The reduction with what placement adds: each labelled pose's tilt from
    its label (column ``label_tilt_deg``, the poses beyond the tolerance
    named in the warnings) and the note on the angles' prior where the
    poses do not determine them."""
    check, warnings = reduction.check, list(reduction.warnings)
    if reduction.positions["source"][0] == "label":
        tilts = label_tilts(check.select(f"a_{s}" for s in AXES).to_numpy(), references(reduction.positions))
        check = check.with_columns(label_tilt_deg=tilts)
        warnings += off_label(tilts, check["label"].to_list(), placement.tolerance_deg)
    notes = reduction.notes + ((placement.prior_note,) if reduction.model == "orthogonal"
                               and isinstance(reduction.chosen, tuple) and "not determined" in reduction.chosen[1] else ())
    tables = tuple(Table("poses", check) if t.name == "poses" else t for t in reduction.tables)
    return replace(reduction, tables=tables, warnings=tuple(warnings), check=check, notes=notes)


def _chosen(positions: pl.DataFrame, dataset: str, choice: ModelChoice | Failure, method: str, fitters: dict[str, Fitter],
            g_local: float, g_uncertainty: float) -> StaticReduction:
    """The reduction of ``choice``: the most general determined model's
    result with the nested orthogonal one beside it, the choice's note and
    the advice on undetermined angles; or the refusal with the pose table."""
    frame = "intrinsic" if method == "orientation-free" else FRAMES[positions["source"][0]]
    general = (choice if isinstance(choice, Failure) else choice.full if not isinstance(choice.full, Failure)
               else choice.orthogonal)
    model = "baseline" if not isinstance(choice, Failure) and general is choice.full else "orthogonal"
    if isinstance(choice, Failure) or isinstance(general, Failure):
        check = _check(positions, dataset, fitters.get(model, reference_fit), None, g_local, g_uncertainty, frame)
        refusal = choice if isinstance(choice, Failure) else Failure(0.0, (
            f"orthogonal axes ({ORTHOGONAL_PARAMETERS[method]}): {getattr(choice.orthogonal, 'reason', '')}; "
            f"{FULL_PARAMETERS[method]}: {getattr(choice.full, 'reason', '')}"))
        return StaticReduction(frame, (), (refusal,), (Table("poses", check),), (), method, None, positions, check)
    check = _check(positions, dataset, fitters[model], general, g_local, g_uncertainty, frame)
    told = (advice(check.select(f"a_{s}" for s in AXES).to_numpy()) if method == "orientation-free"
            else reference_advice(references(positions)) if isinstance(choice.full, Failure) else [])
    nested = (("orthogonal", choice.orthogonal.result),) if model == "baseline" and not isinstance(choice.orthogonal, Failure) else ()
    return StaticReduction(frame, (general.result,), (), (Table("poses", check),), tuple(told), method, general,
                           positions, check, model, nested, (choice.note,), (choice.chosen, choice.reason))
