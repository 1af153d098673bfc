"""The conventions of docs/conventions.md that every stage shares: the table
and DUT frames, the signs and angles of gravity during rotation (Geist 2017
Eq. 5), the intrinsic parameters (Geist 2017 Eq. 14, 16), the device under
test and what the table did at each sample (the forward model's inputs)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

AXES = ("x", "y", "z")
CHANNELS = ("u", "v", "w")
INTRINSIC = ("s_u", "s_v", "s_w", "phi_uv", "phi_vw", "phi_wu", "O_u", "O_v", "O_w")
ANGLE_PAIRS = ((0, 1), (1, 2), (2, 0))  # phi_uv, phi_vw, phi_wu

# Geist 2017 Eq. 5 with the signs of docs/conventions.md: rotation about axis s
# puts gravity at g * (-sin theta) on component SIN_COMPONENT[s] and
# g * cos theta on COS_COMPONENT[s].
SIN_COMPONENT = np.array([1, 0, 0])
COS_COMPONENT = np.array([2, 2, 1])
# theta (seen from the DUT) from the table's right-hand joint angle q.
JOINT_SIGN = {"x": -1.0, "y": 1.0, "z": -1.0}


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
class Motion:
    """What the table did at each sample: the inputs of the forward model.

    ``theta_cmd_deg`` is the commanded angle at the stamp. For rotation
    samples, ``t_start_s`` (the rotation's start) and ``rate_hz`` let
    effects move it to another instant or rate
    (``physics.uniform_angle``). ``temperature_c`` is the DUT's temperature
    at each sample (degree C), None when not recorded.
    """

    t_s: np.ndarray
    axis_idx: np.ndarray
    rotating: np.ndarray
    theta_cmd_deg: np.ndarray
    t_start_s: np.ndarray
    rate_hz: np.ndarray
    t0_s: float = field(default=0.0)
    temperature_c: np.ndarray | None = None
