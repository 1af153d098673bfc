"""What static poses of unknown orientation determine: the nested models of
the orientation-free fit, the choice between them by evidence, and which
angles the poses leave to their small tilts (with the pose that would fix
each).

Two nested models (``multiposition.orientation_free``): ``baseline``, the
nine intrinsic parameters (Geist 2017's model), and ``orthogonal``, six (the
three angles fixed at 90 degrees). Each is fitted where the poses determine
it: more poses than parameters, and directions not on one circle. When both
are, the choice is an F test of the six against the nine (nested least
squares; e.g. Seber and Wild, *Nonlinear Regression*, section 5.3):

    F = ((S_6 - S_9) / 3) / (S_9 / nu),   S = sum_k (|a_k| - g)^2 / (v_k + tau^2)

with both models' residuals weighed by the nine-parameter fit's variances
(pose noise v_k and excess scatter tau^2). The scale is known when the pose
noise alone explains the nine-parameter residuals (tau = 0: S_9 / nu is
taken as 1 and F follows F(3, inf) = chi-square(3) / 3); estimated from the
residuals otherwise (tau > 0, S_9 = nu: F follows F(3, nu)). The orthogonal
model is chosen unless the data reject it at ``SELECTION_LEVEL`` *and* the
nine parameters predict poses left out one at a time better than the six
by more than chance (``heldout``): a rejection driven by poses that scatter
beyond their noise does not carry over to poses not yet seen.

An angle is determined by poses whose gravity mixes its two axes: a pose
*mixes* u and v when 2 |a_u a_v| / |a|^2 >= ``MIXING`` (0.5: gravity at
least 15 degrees from both axes in their plane, at most 75). With none, the
angle rests only on the poses' small tilts, and the advice names the pose
that would fix it.

``f_test`` is the one home of the test for every nested static model (also
``refmodels``, the models of positions of known reference).
``gravity_cone``: poses whose gravity lies within ``MIN_CONE_DEG`` of one
direction determine neither model (with known references checked before
either fit; without, the reason given when neither is determined).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import polars as pl

from rotcal.combine.heldout import HeldOut, compare, press
from rotcal.combine.multiposition import FULL, ORTHOGONAL, TRIL, OrientationFreeFit, magnitude_and_gradient, orientation_free, pose_arrays
from rotcal.combine.poses import OrthogonalReferenceFit, ReferenceFit
from rotcal.model.physics import ANGLE_PAIRS, CHANNELS, INTRINSIC
from rotcal.model.results import Failure
from rotcal.noise.poses import PoseCovariance

MIN_CONE_DEG = 15.0  # poses whose gravity lies within it of one direction determine neither model
SELECTION_LEVEL = 0.01  # the orthogonal model is rejected when the F test's p-value falls below it
MIXING = 0.5  # a pose mixes axes i and j when 2 |a_i a_j| / |a|^2 reaches it (15 to 75 degrees in their plane)
ANGLES = INTRINSIC[3:6]


@dataclass(frozen=True, eq=False)
class ModelChoice:
    """Both models' fits (or why the poses do not determine them), the
    chosen model's name, and the F test between them (NaN when only one is
    determined)."""

    full: OrientationFreeFit | ReferenceFit | Failure
    orthogonal: OrientationFreeFit | OrthogonalReferenceFit | Failure
    chosen: str
    f_statistic: float = float("nan")
    p_value: float = float("nan")
    denominator_dof: float = float("nan")
    heldout: HeldOut | None = None

    @property
    def reason(self) -> str:
        """Why ``chosen`` is the model, in one clause."""
        if np.isnan(self.p_value):
            missing = "baseline" if self.chosen == "orthogonal" else "orthogonal"
            why = getattr(self.full if missing == "baseline" else self.orthogonal, "reason", "")
            return f"the {missing} model is not determined: {why}"
        verdict = "rejects" if self.p_value < SELECTION_LEVEL else "does not reject"
        dof = "inf" if np.isinf(self.denominator_dof) else f"{self.denominator_dof:g}"
        test = (f"the F test of orthogonal axes against the nine parameters {verdict} them at the {SELECTION_LEVEL:g} "
                f"level (F = {self.f_statistic:.3g} with (3, {dof}) degrees of freedom, p = {self.p_value:.3g})")
        full = "nine-parameter" if self.full.__class__.__name__ == "OrientationFreeFit" else "12-parameter"
        return test if self.heldout is None else f"{test}; {self.heldout.text('orthogonal', full)}"

    @property
    def note(self) -> str:
        """The choice in one sentence."""
        both = "" if np.isnan(self.p_value) else "; intrinsic.parquet has both models' rows"
        return f"static model: {self.chosen}: {self.reason}{both}"


def f_test(reduction: float, q: int, scale: float, denominator_dof: float) -> tuple[float, float, float]:
    """F = (reduction / q) / scale of a nested restriction by ``q``
    parameters that raises the weighted sum of squares by ``reduction``,
    its p-value and the denominator's degrees of freedom: F(q, inf) =
    chi-square(q) / q when the scale is known (``denominator_dof`` inf),
    F(q, nu) when it is estimated from the residuals (module docstring).
    The one home of the test for every nested static model."""
    from scipy.special import chdtrc, fdtrc  # here: scipy's import would slow every CLI start

    f = max(reduction, 0.0) / q / scale
    if np.isinf(denominator_dof):
        return f, float(chdtrc(q, q * f)), float("inf")
    return f, float(fdtrc(q, denominator_dof, f)), float(denominator_dof)


def orientation_free_f_test(full: OrientationFreeFit, restricted: OrientationFreeFit, g_local: float) -> tuple[float, float, float]:
    """``f_test`` of the orthogonal orientation-free model against the nine
    parameters, both weighed by the nine-parameter fit's variances (S_9 = nu
    when the excess scatter is estimated, so the scale is one either way)."""
    assert restricted.noise_var is not None
    if full.residual_cov is not None:  # generalised least squares: both weighed by the full model's covariance
        r_full, r_restricted = full.magnitude - g_local, restricted.magnitude - g_local
        s_full = float(r_full @ np.linalg.solve(full.residual_cov, r_full))
        s_restricted = float(r_restricted @ np.linalg.solve(full.residual_cov, r_restricted))
        return f_test(s_restricted - s_full, full.parameters - restricted.parameters, 1.0, float("inf"))
    s_full = float(np.sum((full.magnitude - g_local) ** 2 / full.variance))
    # a restricted fit that took a wander for its misfit (generalised) is weighed by the poses' noise as the full one is
    noise = restricted.noise_var if restricted.residual_cov is None else full.noise_var
    assert noise is not None
    s_restricted = float(np.sum((restricted.magnitude - g_local) ** 2 / (noise + full.excess_std**2)))
    return f_test(s_restricted - s_full, full.parameters - restricted.parameters, 1.0,
                  float("inf") if full.excess_std == 0.0 else float(full.dof))


def choose_model(poses: pl.DataFrame, g_local: float, g_uncertainty: float, misalignment_u: float = 0.0,
                 stated_u: float = 0.0, between: PoseCovariance | None = None) -> ModelChoice:
    """Both models fitted to ``poses`` and the one the evidence chooses; where
    the poses do not determine the nine parameters, the orthogonal model's
    angles carry the prior ``misalignment_u`` (``combine.placement``); the
    nine parameters' angles the datasheet's prior ``stated_u`` where the
    user states one; ``between``: the pose means' covariance between poses
    (``noise.poses``), both fits then generalised least squares."""
    full = orientation_free(poses, g_local, g_uncertainty, FULL, stated_u, between)
    orthogonal = orientation_free(poses, g_local, g_uncertainty, ORTHOGONAL,
                                  misalignment_u if isinstance(full, Failure) else 0.0, between)
    if isinstance(full, Failure) or isinstance(orthogonal, Failure):
        return ModelChoice(full, orthogonal, "orthogonal" if isinstance(full, Failure) else "baseline")
    f, p, dof = orientation_free_f_test(full, orthogonal, g_local)
    held = compare(*(_held_out(fit, poses, g_local, full.variance, free) for fit, free in ((orthogonal, ORTHOGONAL), (full, FULL))))
    return ModelChoice(full, orthogonal, "baseline" if p < SELECTION_LEVEL and held.better else "orthogonal", f, p, dof, held)


def _held_out(fit: OrientationFreeFit, poses: pl.DataFrame, g_local: float, variance: np.ndarray,
              free: np.ndarray) -> np.ndarray:
    """Each pose's squared leave-one-out prediction error of |a| under
    ``fit`` (``heldout.press``), weighed by ``variance``."""
    lower = fit.result.state[:9].reshape(3, 3) / g_local
    params = np.concatenate([lower[TRIL], fit.result.state[9:]])
    magnitude, _, jac = magnitude_and_gradient(params, pose_arrays(poses)[0])
    weight = 1.0 / np.sqrt(variance)
    return press((magnitude - g_local) * weight, jac[:, free] * weight[:, None])


def gravity_cone(directions: np.ndarray) -> str | None:
    """Why the poses determine neither model when their gravity directions
    (n, 3; any length) all lie within ``MIN_CONE_DEG`` of their mean
    direction, else None: along that direction offsets and sensitivities
    cannot be told apart (one pose's worth of information, repeated)."""
    d = directions / np.linalg.norm(directions, axis=1)[:, None]
    mean = d.mean(axis=0)
    if not np.all(np.isfinite(mean)) or np.linalg.norm(mean) == 0.0:
        return None
    spread = float(np.degrees(np.arccos(np.clip(d @ (mean / np.linalg.norm(mean)), -1.0, 1.0))).max())
    if spread >= MIN_CONE_DEG:
        return None
    return (f"the poses' gravity lies within {spread:.2g} degrees of one direction (at least {MIN_CONE_DEG:g} are needed): "
            "along it offsets and sensitivities cannot be told apart, so the poses determine neither the nine intrinsic "
            "parameters nor the six of orthogonal axes; add poses with gravity along each axis, up and down")


def mixing(directions: np.ndarray) -> np.ndarray:
    """(n, 3): whether each pose mixes the axes of phi_uv, phi_vw, phi_wu."""
    d = directions / np.linalg.norm(directions, axis=1)[:, None]
    return np.column_stack([2 * np.abs(d[:, i] * d[:, j]) >= MIXING for i, j in ANGLE_PAIRS])


def determines(directions: np.ndarray) -> list[str]:
    """Per pose, the angles it mixes (space-separated; empty for none)."""
    return [" ".join(a for a, hit in zip(ANGLES, row) if hit) for row in mixing(directions)]


def advice(directions: np.ndarray) -> list[str]:
    """One sentence per angle no pose mixes, naming the pose that fixes it."""
    hits = mixing(directions)
    return [f"the poses barely determine {angle}: none mixes {CHANNELS[i]} and {CHANNELS[j]} "
            f"(2 |a_{CHANNELS[i]} a_{CHANNELS[j]}| / |a|^2 >= {MIXING:g}), so it rests on their small tilts; "
            f"a pose between +{CHANNELS[i]} and +{CHANNELS[j]} (gravity about 45 degrees from both) fixes {angle}"
            for k, (angle, (i, j)) in enumerate(zip(ANGLES, ANGLE_PAIRS)) if not hits[:, k].any()]
