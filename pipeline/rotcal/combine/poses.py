"""Static positions of a recording, with what is known about each one's
reference acceleration, and the calibration against known references.

A *pose table* has one row per static position: its mean output and the
covariance of that mean, its mean temperature, and its reference
acceleration ``ref_x, ref_y, ref_z`` in g (the reading of an ideal triad
aligned with the reference frame, AN4399's G_p) where it is known:

- labelled poses (imucal's ``x_p``, ``x_a``, ...): that axis reads +1 g or
  -1 g, the others 0, in the frame of the DUT's case;
- jig positions: ``gx, gy, gz`` as recorded (docs/inputs.md);
- table steps: gravity of docs/conventions.md at the step's angle, in the
  table frame;
- still intervals found by ``stillness``: unknown (null).

``reference_fit`` is the forward model of Geist 2017 Eq. 19 fitted to
positions with known references: R_k = O + (g r) . ref_k per channel, an
ordinary least-squares fit of 12 parameters (``lsq.ols``), whose
responsivity rows give the nine intrinsic parameters.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.multiposition import pose_arrays
from rotcal.errors import UndeterminedError
from rotcal.fit.lsq import LinearFit, least_squares_solution, ols
from rotcal.fit.means import channel_wander, group_statistics
from rotcal.fit.segments import segment_rows
from rotcal.model.columns import Outputs, sample_step, selected_rows
from rotcal.model.physics import AXES, CHANNELS, axis_index, gravity_direction
from rotcal.model.results import Failure, IntrinsicResult, whole_fit_input
from rotcal.noise.poses import PoseCovariance
from rotcal.segment.stillness import StillnessConfig, still_and_short, unused_rows

LABEL_REFERENCE = {f"{axis}_{side}": tuple(float(sign * (a == axis)) for a in AXES)
                   for axis in AXES for side, sign in (("p", 1), ("a", -1))}
REFERENCE = ("ref_x", "ref_y", "ref_z")
MIN_REFERENCE_POSES = 4


def _pose_frame(samples: pl.DataFrame, group: np.ndarray, n_groups: int, source: str,
                label: Sequence[str | None], reference: np.ndarray) -> pl.DataFrame:
    """One row per group of samples (``group`` = -1 outside every pose)."""
    t_ns = samples["t_ns"].to_numpy()
    # the outputs' columns, as samples.select(CHANNELS).to_numpy() orders them (no copy of the table's)
    counts, means, cov = group_statistics(Outputs.of_frame(samples, fortran=True), group, n_groups)
    at = selected_rows(group >= 0)
    g = group[at]
    temperature = np.full(n_groups, np.nan)
    if samples["temperature_c"].null_count() < samples.height:  # (none recorded: NaN, without a column of NaN)
        temp = samples["temperature_c"].fill_null(np.nan).to_numpy()[at]
        known = np.isfinite(temp)
        t_n = np.bincount(g[known], minlength=n_groups)
        np.divide(np.bincount(g[known], weights=temp[known], minlength=n_groups), t_n, out=temperature, where=t_n > 0)
    first = np.full(n_groups, np.iinfo(np.int64).max)
    last = np.full(n_groups, np.iinfo(np.int64).min)
    np.minimum.at(first, g, t_ns[at])
    np.maximum.at(last, g, t_ns[at])
    return _statistics_frame(source, label, reference, counts, means, cov, temperature, first, last)


def _statistics_frame(source: str, label: Sequence[str | None], reference: np.ndarray, counts: np.ndarray,
                      means: np.ndarray, cov: np.ndarray, temperature: np.ndarray,
                      first: np.ndarray | None = None, last: np.ndarray | None = None) -> pl.DataFrame:
    """The pose table from each pose's statistics: sample count, mean (n, 3),
    covariance of the mean (n, 3, 3), mean temperature and first and last
    time stamp (null for pose summaries, which have none)."""
    n_groups = len(counts)
    none = [None] * n_groups
    return pl.DataFrame({
        "pose": np.arange(n_groups, dtype=np.int64), "label": pl.Series(label, dtype=pl.String),
        "source": [source] * n_groups, "t_start_ns": pl.Series(none if first is None else first, dtype=pl.Int64),
        "t_end_ns": pl.Series(none if last is None else last, dtype=pl.Int64), "n_samples": counts, "temperature_c": temperature,
        **{f"mean_{c}": means[:, r] for r, c in enumerate(CHANNELS)},
        "cov_mean": cov.reshape(-1, 9).tolist(),
        **{name: reference[:, i] for i, name in enumerate(REFERENCE)},
    }, schema_overrides={"cov_mean": pl.List(pl.Float64)})


def _references(labels: list[str | None], jig: np.ndarray) -> tuple[np.ndarray, str]:
    """Each pose's reference (g): its label's, else the jig's ``gx, gy, gz``;
    and the source, ``label`` when every pose is labelled, else ``jig``."""
    reference = np.array([LABEL_REFERENCE[lab] if lab is not None else jig[k] for k, lab in enumerate(labels)], float)
    return reference.reshape(-1, 3), "label" if all(lab is not None for lab in labels) else "jig"


def summary_poses(summaries: pl.DataFrame) -> pl.DataFrame:
    """The pose table of pose summaries (``ingest.summaries``: a label or
    ``gx, gy, gz``, and per channel the mean, the sample standard deviation
    s and the count n, optionally the channels' correlations r): the
    statistics ``group_statistics`` takes from the samples, the covariance
    of the mean s_i r_ij s_j / sqrt(n_i n_j) (r = 0 between channels where
    not given; zero for pose means without scatter)."""
    labels = summaries["pose"].to_list()
    reference, source = _references(labels, summaries.select("gx", "gy", "gz").to_numpy())
    if all(label is None for label in labels) and np.isnan(reference).all():
        source = "stillness"  # no pose says how it rested: poses of unknown orientation
    means = summaries.select(f"{c}_mean" for c in CHANNELS).to_numpy()
    # standard deviations of the means, s / sqrt(n), and the channels' correlations (0 where not given)
    std = (summaries.select(f"{c}_std" for c in CHANNELS).to_numpy()
           / np.sqrt(summaries.select(f"{c}_n" for c in CHANNELS).to_numpy()))
    corr = np.broadcast_to(np.eye(3), (summaries.height, 3, 3)).copy()
    for (i, j), name in zip(((0, 1), (1, 2), (2, 0)), ("corr_uv", "corr_vw", "corr_wu")):
        corr[:, i, j] = corr[:, j, i] = summaries[name].fill_null(0.0).to_numpy()
    cov = std[:, :, None] * corr * std[:, None, :]
    counts = summaries.select(pl.min_horizontal(f"{c}_n" for c in CHANNELS)).to_series().to_numpy()
    return _statistics_frame(source, labels, reference, counts, means, cov,
                             summaries["temperature_c"].fill_null(np.nan).to_numpy())


def labelled_poses(samples: pl.DataFrame, segments: pl.DataFrame) -> pl.DataFrame:
    """The ``pose`` segments (pose labels or jig ``gx, gy, gz``) as poses
    with their reference accelerations; every sample of a segment counts
    (the labels say where the DUT rests)."""
    ids = segments.filter(pl.col("kind") == "pose")["segment"].to_list()
    group = samples.select(pl.col("segment").replace_strict(ids, list(range(len(ids))), default=-1,
                                                            return_dtype=pl.Int64)).to_series().to_numpy()
    if not ids:
        return _pose_frame(samples, group, 0, "label", [], np.zeros((0, 3)))
    firsts = samples.filter(pl.Series(group >= 0)).with_columns(_g=pl.Series(group[group >= 0])) \
        .group_by("_g", maintain_order=True).agg(pl.col("pose").first(), pl.col("gx", "gy", "gz").mean()).sort("_g")
    reference, source = _references(firsts["pose"].to_list(), firsts.select("gx", "gy", "gz").to_numpy())
    return _pose_frame(samples, group, len(ids), source, firsts["pose"].to_list(), reference)


def table_step_poses(samples: pl.DataFrame, segments: pl.DataFrame) -> pl.DataFrame:
    """Every step of the static table segments as a pose, its reference the
    gravity of docs/conventions.md at the commanded angle."""
    static = segments.filter((pl.col("kind") == "static") & (pl.col("angle_source") != "none"))["segment"]
    rows = segment_rows(samples)
    # the static segments' rows only: a few thousand of a capture's millions
    samples = pl.concat([samples.slice(*rows[s]) for s in static.to_list() if s in rows] or [samples.clear()])
    # a step is a run of rows of one segment at one commanded angle (two missing angles alike)
    segment, angle = samples["segment"].to_numpy(), samples["angle_deg"].fill_null(np.nan).to_numpy()
    new_step = np.ones(samples.height, bool)
    new_step[1:] = (segment[1:] != segment[:-1]) | ~((angle[1:] == angle[:-1]) | (np.isnan(angle[1:]) & np.isnan(angle[:-1])))
    group = np.cumsum(new_step) - 1
    first = np.flatnonzero(new_step)
    axes = samples["axis"].gather(first).to_list()
    reference = gravity_direction(np.array([axis_index(a) for a in axes], dtype=np.int64), angle[first]) \
        if first.size else np.zeros((0, 3))
    labels = [f"{a} {theta:g} deg" for a, theta in zip(axes, angle[first].tolist())]
    return _pose_frame(samples, group, first.size, "table step", labels, reference)


def without_scatter(poses: pl.DataFrame) -> bool:
    """Whether the poses are means without scatter (one row each: no pose noise known)."""
    return poses.height > 0 and not np.any(pose_arrays(poses)[1])


def scatterless_poses(poses: pl.DataFrame) -> pl.DataFrame:
    """Poses of one sample each taken as means without scatter: their covariance zero, not undefined."""
    return poses.with_columns(cov_mean=pl.Series([[0.0] * 9] * poses.height, dtype=pl.List(pl.Float64)))


def sample_poses(samples: pl.DataFrame) -> pl.DataFrame:
    """Every sample a pose mean of unknown orientation (``[format]
    pose_means``: a file of one row per pose, Magneto's input)."""
    n = samples.height
    poses = _pose_frame(samples, np.arange(n), n, "stillness", [None] * n, np.full((n, 3), np.nan))
    return scatterless_poses(poses)


def still_poses(samples: pl.DataFrame, config: StillnessConfig = StillnessConfig(), dataset: str = ""
                ) -> tuple[pl.DataFrame, pl.DataFrame]:
    """The still intervals of a recording (``stillness``) as poses of
    unknown orientation, and the detector's rejections (a rest too short,
    or too noisy) as rows of ``still_unused``."""
    t_ns = samples["t_ns"].to_numpy()
    # the outputs' columns, as samples.select(CHANNELS).to_numpy() orders them (no copy of the table's)
    intervals, short = still_and_short(t_ns, Outputs.of_frame(samples, fortran=True), config)
    group = np.full(samples.height, -1, np.int64)
    for k, (a, b) in enumerate(intervals.select("start", "stop").iter_rows()):  # intervals do not overlap
        group[a:b] = k
    poses = _pose_frame(samples, group, intervals.height, "stillness", [None] * intervals.height,
                        np.full((intervals.height, 3), np.nan))
    capture = samples["capture"].gather(short["start"]) if "capture" in samples.columns else ""
    interval_s = sample_step(t_ns) / 1e9 if t_ns.size > 1 else 0.0
    return poses, unused_rows(dataset, capture, short, interval_s)


def references(poses: pl.DataFrame) -> np.ndarray:
    return poses.select(REFERENCE).to_numpy()


@dataclass(frozen=True, eq=False)
class ReferenceFit:
    """The 12-parameter forward fit R_k = O + C ref_k (C = g r, output units
    per g): the intrinsic result, the residuals (n, 3) in output units, the
    residual degrees of freedom (3 (n - 4)), the excess scatter per channel
    (output units) and the reduced chi-square of the pose noise alone."""

    result: IntrinsicResult
    residuals: np.ndarray
    dof: int
    excess_cov: np.ndarray
    chi2_reduced: float
    pose_cov: PoseCovariance | None = None  # generalised least squares: the pose means' covariance it weighed them by

    @property
    def excess_std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.excess_cov))


@dataclass(frozen=True, eq=False)
class OrthogonalReferenceFit:
    """The nested fit of orthogonal axes, C = D R (``refmodels``): the
    intrinsic result (angles 90 degrees), the rotation R, the residuals
    (n, 3) in output units, their degrees of freedom (3 n - 9), the excess
    covariance T and the channels' common weights (their weighted sum of
    squares ``sum_sq``)."""

    result: IntrinsicResult
    rotation: np.ndarray
    residuals: np.ndarray
    dof: int
    excess_cov: np.ndarray
    weights: np.ndarray

    @property
    def sum_sq(self) -> float:
        return float(np.sum(self.residuals**2 * self.weights))


def generalised_fit(design: np.ndarray, m: np.ndarray, between: PoseCovariance) -> tuple[LinearFit, PoseCovariance] | None:
    """Generalised least squares of each channel of the pose means ``m``
    (n, 3) on ``design`` (n, p) under the pose means' covariance between
    poses with the wander their scatter shows beyond it
    (``noise.poses.channel_wander``): per channel (X' V_r^-1 X)^-1 X' V_r^-1,
    the channels independent; and the covariance with the wander. None
    where that covariance is the poses' own alone and their scatter shows
    no wander (``ols`` as it was). Raises
    ``UndeterminedError`` as ``ols`` does. (The excess covariance is zero:
    the wander stands for the scatter beyond the noise.)"""
    least_squares_solution(design)  # the design's conditioning, as ``ols`` checks it
    wandering = channel_wander(between, design, m)
    if between.plain and wandering is between:
        return None
    total = wandering.channels
    n, p = design.shape
    gains = []
    for r in range(3):
        weighed = np.linalg.solve(total[r], design)  # V_r^-1 X
        gains.append(np.linalg.solve(design.T @ weighed, weighed.T))  # (p, n)
    coef = np.column_stack([a @ m[:, r] for r, a in enumerate(gains)])
    resid = m - design @ coef
    out = np.zeros((3 * p, 3 * p))
    for r in range(3):  # the channels' noise independent, as the noise model is per channel (``PoseCovariance.projected``)
        out[r * p:(r + 1) * p, r * p:(r + 1) * p] = gains[r] @ total[r] @ gains[r].T
    chi2 = float(sum(resid[:, r] @ np.linalg.solve(total[r], resid[:, r]) for r in range(3)))
    return LinearFit(coef, out, resid, np.zeros((3, 3)), n - p, chi2), wandering


def reference_fit(poses: pl.DataFrame, g_local: float, g_uncertainty: float,
                  between: PoseCovariance | None = None) -> ReferenceFit | Failure:
    """Responsivity rows and offsets from positions of known reference
    acceleration (Geist 2017 Eq. 19; ordinary least squares on the pose
    means, the normal equations of AN4399 Eq. 34 per channel; with
    ``between``, the pose means' covariance between poses, generalised
    least squares, ``generalised_fit``)."""
    n = poses.height
    if n < MIN_REFERENCE_POSES:
        return Failure(0.0, f"{n} positions with a known reference: at least {MIN_REFERENCE_POSES} "
                           "are needed for the 12 parameters")
    m, cov = pose_arrays(poses)
    design = np.column_stack([references(poses), np.ones(n)])
    try:
        generalised = generalised_fit(design, m, between) if between is not None and n > 4 else None
        fit, between = (ols(design, m, cov), None) if generalised is None else generalised
    except UndeterminedError as exc:
        return Failure(0.0, f"the reference accelerations do not determine the 12 parameters: {exc.problem}")
    # coefficient order (channel, [ref_x, ref_y, ref_z, 1]) -> state (g r_u, g r_v, g r_w, O)
    order = np.array([4 * r + i for r in range(3) for i in range(3)] + [4 * r + 3 for r in range(3)])
    state = fit.coef.T.ravel()[order]
    state_cov = fit.cov[np.ix_(order, order)]
    dof = 3 * fit.dof
    noise_free = np.all(np.einsum("kii->ki", cov) <= (1e-12 * np.abs(m).max()) ** 2)  # rounding of identical samples
    if dof == 0 and noise_free:
        # an exact fit to positions without noise: the values are exact, but nothing, neither residuals
        # nor the poses' scatter, gives them an uncertainty
        return Failure(0.0, f"{n} positions with a known reference and no scatter determine the 12 parameters "
                           "exactly, with no residual degree of freedom: their uncertainty is undetermined (the "
                           "AN4399 correction gives the exact values); record at least 5 positions")
    # the positions' noise alone where the fit is exact: its degrees of freedom are the pose means' own
    noise_dof = float(dof) if dof else float(max(int(poses["n_samples"].to_numpy().min()) - 1, 1))
    # the positions' noise and excess scatter together: the sandwich covariance of one fit
    result = IntrinsicResult.from_state(0.0, state, state_cov, g_local, g_uncertainty,
                                        [(whole_fit_input("positions", noise_dof), state_cov)])
    return ReferenceFit(result, fit.residuals, dof, fit.excess_cov, fit.chi2 / dof if dof else float("nan"), between)


@dataclass(frozen=True, eq=False)
class CorrectedPoses:
    """Pose means corrected by a result: acceleration (n, 3) in the result's
    frame (m/s^2), |a| and its standard uncertainty, and |a| with offsets
    and sensitivities alone (the axes taken as orthogonal)."""

    acceleration: np.ndarray
    magnitude: np.ndarray
    magnitude_u: np.ndarray
    magnitude_orthogonal: np.ndarray


def correct_poses(result: IntrinsicResult, m: np.ndarray, cov: np.ndarray, extra_var: float | np.ndarray = 0.0) -> CorrectedPoses:
    """a_k = g S^-1 (m_k - O), S the rows g r of the result's state
    (Geist 2017 Eq. 18 with P = S^-1 g).

    The uncertainty of |a| combines the result's state covariance, the pose
    noise ``cov`` (n, 3, 3) and ``extra_var`` (m/s^2)^2; it leaves out
    g_local's, which scales |a| and g alike.
    """
    g = result.g_local
    S = result.state[:9].reshape(3, 3)
    offsets = result.state[9:]
    b = np.linalg.solve(S, (m - offsets).T).T
    a = g * b
    mag = np.linalg.norm(a, axis=1)
    h = np.linalg.solve(S.T, (a / mag[:, None]).T).T  # d|a|/dm = g h
    grad_state = np.hstack([(-g * h[:, :, None] * b[:, None, :]).reshape(-1, 9), -g * h])
    var = (np.einsum("ki,ij,kj->k", grad_state, result.state_cov, grad_state)
           + g**2 * np.einsum("ki,kij,kj->k", h, cov, h) + extra_var)
    s = result.value[:3]
    orthogonal = np.linalg.norm((m - offsets) / s, axis=1)
    return CorrectedPoses(a, mag, np.sqrt(var), orthogonal)
