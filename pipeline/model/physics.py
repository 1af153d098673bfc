"""The measurement model: conventions of contract section 1 and the forward
model with the effects of ``effects.md``, in the order that page gives.

The simulator and the diagnosis both evaluate this one model, so what rotcal
simulates is exactly what it fits.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

AXES = ("x", "y", "z")
CHANNELS = ("u", "v", "w")
INTRINSIC = ("s_u", "s_v", "s_w", "phi_uv", "phi_vw", "phi_wu", "O_u", "O_v", "O_w")
ANGLE_PAIRS = ((0, 1), (1, 2), (2, 0))  # phi_uv, phi_vw, phi_wu

# Geist 2017 Eq. 5 with the signs of contract section 1: rotation about axis s
# puts gravity at g * (-sin theta) on component SIN_COMPONENT[s] and
# g * cos theta on COS_COMPONENT[s].
SIN_COMPONENT = np.array([1, 0, 0])
COS_COMPONENT = np.array([2, 2, 1])
# theta (seen from the DUT) from the table's right-hand joint angle q.
JOINT_SIGN = {"x": -1.0, "y": 1.0, "z": -1.0}

STANDARD_GRAVITY = 9.80665
STANDARD_GRAVITY_UNCERTAINTY = 0.02


def axis_index(axis: str) -> int:
    return AXES.index(axis)


def gravity_direction(axis_idx: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """Unit gravity vector (pointing up) in the table frame, Geist 2017 Eq. 5.

    ``axis_idx`` (0, 1, 2 for x, y, z) and ``theta_deg`` are per sample;
    returns an (n, 3) array.
    """
    theta = np.deg2rad(theta_deg)
    out = np.zeros((theta.size, 3))
    rows = np.arange(theta.size)
    out[rows, SIN_COMPONENT[axis_idx]] = -np.sin(theta)
    out[rows, COS_COMPONENT[axis_idx]] = np.cos(theta)
    return out


def gravity_direction_derivative(axis_idx: np.ndarray, theta_deg: np.ndarray) -> np.ndarray:
    """d(gravity_direction)/d(theta) per degree of theta, (n, 3)."""
    theta = np.deg2rad(theta_deg)
    out = np.zeros((theta.size, 3))
    rows = np.arange(theta.size)
    out[rows, SIN_COMPONENT[axis_idx]] = -np.cos(theta) * (np.pi / 180.0)
    out[rows, COS_COMPONENT[axis_idx]] = -np.sin(theta) * (np.pi / 180.0)
    return out


def unit_vectors_from_angles(phi_uv: float, phi_vw: float, phi_wu: float) -> np.ndarray:
    """Right-handed unit vectors u, v, w (rows) with the given angles in degrees.

    u along x, v in the x-y plane: the intrinsic frame in which the intrinsic
    parameters fix the vectors up to a common rotation.
    """
    c_uv, c_vw, c_wu = np.cos(np.deg2rad([phi_uv, phi_vw, phi_wu]))
    s_uv = np.sin(np.deg2rad(phi_uv))
    a = c_wu
    b = (c_vw - c_uv * a) / s_uv
    c = np.sqrt(1.0 - a * a - b * b)
    return np.array([[1.0, 0.0, 0.0], [c_uv, s_uv, 0.0], [a, b, c]])


def rotation_matrix(axis_vector: np.ndarray, angle_deg: float) -> np.ndarray:
    """Rodrigues rotation by ``angle_deg`` about ``axis_vector``."""
    k = np.asarray(axis_vector, float) / np.linalg.norm(axis_vector)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.deg2rad(angle_deg)
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * kx @ kx


def intrinsic_from_vectors(responsivity: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """The nine intrinsic parameters (order ``INTRINSIC``) of responsivity rows.

    Geist 2017 Eq. 14 (lengths) and Eq. 16 (angles, in degrees). Leading
    dimensions broadcast: (..., 3, 3) rows and (..., 3) offsets give (..., 9),
    so a Monte Carlo sample is evaluated in one call.
    """
    s = np.sqrt(np.einsum("...ij,...ij->...i", responsivity, responsivity))
    unit = responsivity / s[..., None]
    first, second = (list(k) for k in zip(*ANGLE_PAIRS))
    cos = np.einsum("...ij,...ij->...i", unit[..., first, :], unit[..., second, :])
    return np.concatenate([s, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), offsets], axis=-1)


@dataclass(frozen=True)
class Dut:
    """A device under test: responsivity rows u, v, w in the table frame
    (output unit per m/s^2), offsets (output unit), white noise per channel."""

    responsivity: np.ndarray
    offsets: np.ndarray
    noise_std: np.ndarray
    full_scale: float | None = 32767.0
    integer_output: bool = True


@dataclass(frozen=True)
class AxisEffect:
    """A per-rotation-axis effect parameter set (centripetal, ripple, tilt)."""

    axis: str
    values: tuple[float, ...]


@dataclass(frozen=True)
class Effects:
    """The physics of ``effects.md``; all zero is the papers' linear model.

    centripetal: per axis, ``values`` = the table-frame vector d (m), with
        the component along the axis zero.
    rate_ripple: per axis, ``values`` = (ripple_deg, ripple_phase_deg).
    axis_tilt: per axis, ``values`` = (tilt_deg,).
    """

    centripetal: tuple[AxisEffect, ...] = ()
    k3: tuple[float, float, float] = (0.0, 0.0, 0.0)
    k2: tuple[float, float, float] = (0.0, 0.0, 0.0)
    clip_low: float | None = None
    clip_high: float | None = None
    delay_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rate_error: float = 0.0
    rate_ripple: tuple[AxisEffect, ...] = ()
    axis_tilt: tuple[AxisEffect, ...] = ()
    drift: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def per_axis(self, name: str) -> dict[int, np.ndarray]:
        return {axis_index(e.axis): np.asarray(e.values, float) for e in getattr(self, name)}


@dataclass(frozen=True)
class Motion:
    """What the table did at each sample: the inputs of the forward model.

    ``theta_cmd_deg`` is the commanded angle at the stamp. For rotation
    samples, ``theta0_deg``, ``t_start_s`` and ``rate_hz`` describe the
    commanded rotation theta0 + 360 rate (t - t_start) so that effects can
    re-evaluate it at another instant or rate.
    """

    t_s: np.ndarray
    axis_idx: np.ndarray
    rotating: np.ndarray
    theta_cmd_deg: np.ndarray
    theta0_deg: np.ndarray
    t_start_s: np.ndarray
    rate_hz: np.ndarray
    t0_s: float = field(default=0.0)


def uniform_angle(motion: Motion, effects: Effects, delay_s: float) -> np.ndarray:
    """The rotating samples' angle at the true rate, before ripple:
    theta0 + 360 rate (1 + e) (t + delay - t_start)."""
    rot = motion.rotating
    elapsed = motion.t_s[rot] + delay_s - motion.t_start_s[rot]
    return motion.theta0_deg[rot] + 360.0 * motion.rate_hz[rot] * (1.0 + effects.rate_error) * elapsed


def true_angle(motion: Motion, effects: Effects, delay_s: float) -> np.ndarray:
    """The true table angle seen by a channel sampled ``delay_s`` after its stamp.

    ``rate_error`` rescales the commanded rate, then ``rate_ripple`` adds a
    once-per-revolution term; static steps are exact (effects.md, order).
    """
    rot = motion.rotating
    theta = motion.theta_cmd_deg.astype(float).copy()
    base = uniform_angle(motion, effects, delay_s)
    ripple = np.zeros_like(base)
    for ax, (amp, phase) in effects.per_axis("rate_ripple").items():
        on = motion.axis_idx[rot] == ax
        ripple[on] = amp * np.sin(np.deg2rad(base[on] + phase))
    theta[rot] = base + ripple
    return theta


def specific_force(motion: Motion, effects: Effects, g_local: float, delay_s: float) -> np.ndarray:
    """Specific force (m/s^2, table frame) for a channel sampled ``delay_s`` late.

    Gravity of Geist Eq. 5 with ``axis_tilt`` (a -> cos(tilt) a + g sin(tilt)
    s_hat) plus ``centripetal`` (a -> a - w^2 d) on rotation samples.
    """
    theta = true_angle(motion, effects, delay_s)
    a = g_local * gravity_direction(motion.axis_idx, theta)
    for ax, (tilt_deg,) in effects.per_axis("axis_tilt").items():
        on = motion.axis_idx == ax
        a[on] *= np.cos(np.deg2rad(tilt_deg))
        a[on, ax] += g_local * np.sin(np.deg2rad(tilt_deg))
    for ax, d in effects.per_axis("centripetal").items():
        on = motion.rotating & (motion.axis_idx == ax)
        omega = 2 * np.pi * motion.rate_hz[on] * (1.0 + effects.rate_error)
        a[on] -= (omega**2)[:, None] * d[None, :]
    return a


def channel_forces(motion: Motion, effects: Effects, g_local: float) -> list[np.ndarray]:
    """The specific force each channel sees (its own sampling instant)."""
    delays = np.asarray(effects.delay_s, float)
    if not np.any(delays):
        return [specific_force(motion, effects, g_local, 0.0)] * 3
    return [specific_force(motion, effects, g_local, delays[r]) for r in range(3)]


def nonlinearity(y: np.ndarray, x1g: np.ndarray, effects: Effects) -> np.ndarray:
    """The gain errors of effects.md acting on the offset-free output y."""
    ratio = y / x1g
    return y * (1.0 + np.asarray(effects.k3) * ratio**2) * (1.0 + np.asarray(effects.k2) * ratio)


def drift_term(motion: Motion, effects: Effects) -> np.ndarray:
    return np.asarray(effects.drift)[None, :] * (motion.t_s - motion.t0_s)[:, None]


def noise_free_output(motion: Motion, dut: Dut, effects: Effects, g_local: float) -> np.ndarray:
    """Outputs (n, 3) before noise, rounding and clipping (effects.md order)."""
    forces = channel_forces(motion, effects, g_local)
    y = np.column_stack([forces[r] @ dut.responsivity[r] for r in range(3)])
    x1g = np.linalg.norm(dut.responsivity, axis=1) * g_local
    return dut.offsets[None, :] + drift_term(motion, effects) + nonlinearity(y, x1g, effects)


def observe(clean: np.ndarray, dut: Dut, effects: Effects, rng: np.random.Generator) -> np.ndarray:
    """Add white noise, round to the integer output and clip (effects.md order)."""
    out = clean + rng.standard_normal(clean.shape) * np.asarray(dut.noise_std)[None, :]
    if dut.integer_output:
        out = np.round(out)
    low = -np.inf if effects.clip_low is None else effects.clip_low
    high = np.inf if effects.clip_high is None else effects.clip_high
    if dut.full_scale is not None:
        low, high = max(low, -dut.full_scale - 1.0), min(high, dut.full_scale)
    return np.clip(out, low, high)
