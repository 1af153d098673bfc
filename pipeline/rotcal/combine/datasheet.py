"""What a datasheet knows about sensitivities and offsets, as Type B
information (GUM 4.3) joined to what the poses determine.

A datasheet bounds each axis's sensitivity about its nominal value
(``[device] sensitivity``, output unit per standard g, within
``sensitivity_tolerance``, a fraction) and its zero-g offset about zero
(``offset_tolerance``, output units, one value or one per axis). rotcal
takes each bound as a rectangular distribution (GUM 4.3.7: u = bound /
sqrt(3)) and joins it to the fit as one more observation of the parameter
(a linearised Bayesian update, the Kalman form of weighted least squares):

    x' = x + K (x0 - h(x)),  K = P H' (H P H' + R)^-1,
    P' = (I - K H) P (I - K H)' + K R K'

with h the stated parameters as functions of the state, H their Jacobian
and R the priors' variances. Each of the fit's input groups keeps its share
(I - K H) P_i (I - K H)'; the datasheet is one more input group, K R K', of
infinite degrees of freedom. A parameter the poses determine well barely
moves (its prior weight is tiny); one they barely determine rests on the
prior, and its published uncertainty never exceeds the prior's. The result
names the parameters whose prior outweighs the data (u from the data above
u of the prior).
"""

from __future__ import annotations

import numpy as np

from rotcal.model.constants import STANDARD_GRAVITY
from rotcal.model.physics import INTRINSIC
from rotcal.model.placement import Placement
from rotcal.model.results import IntrinsicResult, intrinsic_jacobian, whole_fit_input

PRIOR_INPUT = "datasheet prior"
AGREEMENT = 3.0  # a prior farther than this many combined standard uncertainties from the data is not joined


def datasheet_priors(placement: Placement) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The stated priors: indices into the nine parameters (``INTRINSIC``),
    their values (sensitivities in output unit per m/s^2, offsets in output
    units) and standard uncertainties (rectangular, GUM 4.3.7)."""
    index, value, u = [], [], []
    if placement.sensitivity is not None and placement.sensitivity_tolerance is not None:
        s0 = placement.sensitivity / STANDARD_GRAVITY
        index += [0, 1, 2]
        value += [s0] * 3
        u += [s0 * placement.sensitivity_tolerance / np.sqrt(3.0)] * 3
    if placement.offset_tolerance is not None:
        index += [6, 7, 8]
        value += [0.0] * 3
        u += list(np.broadcast_to(np.asarray(placement.offset_tolerance, float), 3) / np.sqrt(3.0))
    return np.array(index, int), np.array(value, float), np.array(u, float)


def with_datasheet(result: IntrinsicResult, placement: Placement) -> tuple[IntrinsicResult, str | None]:
    """``result`` joined to the datasheet's priors (module docstring), and a
    note naming the parameters that rest on the prior (None without priors).
    A prior the data contradict (the estimate farther from it than
    ``AGREEMENT`` combined standard uncertainties: a nominal of another
    range, or an output whose zero-g level is not 0) is not joined, and the
    note names it."""
    index, prior, prior_u = datasheet_priors(placement)
    if not index.size:
        return result, None
    value, jac, _ = intrinsic_jacobian(result.state, result.g_local)
    data_u = np.sqrt(np.einsum("ij,jk,ik->i", jac[index], result.state_cov, jac[index]))
    agree = np.abs(value[index] - prior) <= AGREEMENT * np.hypot(data_u, prior_u)
    stated = ", ".join(name for name, on in (("sensitivity_tolerance", 0 in index), ("offset_tolerance", 6 in index)) if on)
    joined = _joined(result, value, jac, index[agree], prior[agree], prior_u[agree]) if agree.any() else result
    resting = [INTRINSIC[i] for i, d, p in zip(index[agree], data_u[agree], prior_u[agree]) if d > p]
    note = (f"datasheet priors ([device] {stated}) joined as Type B inputs (GUM 4.3, rectangular): "
            + (f"{', '.join(resting)} rest on the prior (the poses determine them less well than the datasheet)"
               if resting else "every parameter they bound is determined by the poses better than by the datasheet"))
    if not agree.all():
        note += (f"; not joined, the data contradicting their prior beyond {AGREEMENT:g} standard uncertainties: "
                 + ", ".join(f"{INTRINSIC[i]} ({value[i]:.6g} against {p:.6g})" for i, p in zip(index[~agree], prior[~agree]))
                 + " (the nominal of another range? an output whose zero-g level is not 0?)")
    return joined, note


def _joined(result: IntrinsicResult, value: np.ndarray, jac: np.ndarray, index: np.ndarray, prior: np.ndarray,
            prior_u: np.ndarray) -> IntrinsicResult:
    """The linearised Bayesian update of ``result`` by the priors of the
    parameters ``index`` (module docstring), the prior one more input group."""
    H = jac[index]
    P = result.state_cov
    R = np.diag(prior_u**2)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    state = result.state + K @ (prior - value[index])
    keep = np.eye(P.shape[0]) - K @ H
    parts = [(inp, keep @ part @ keep.T) for inp, part in zip(result.inputs, result.state_parts)]
    parts.append((whole_fit_input(PRIOR_INPUT, float("inf")), K @ R @ K.T))
    state_cov = sum(part for _, part in parts)
    return IntrinsicResult.from_state(result.rate_hz, state, state_cov, result.g_local, result.g_uncertainty, parts)
