"""The measurement conventions of docs/conventions.md, checked by hand."""

import numpy as np
import pytest

from rotcal.model.physics import (
    ANGLE_PAIRS,
    gravity_direction,
    intrinsic_from_vectors,
    rotation_matrix,
    unit_vectors_from_angles,
)


@pytest.mark.parametrize(
    "axis, theta, expected",
    [
        (0, 30.0, (0.0, -0.5, np.sqrt(3) / 2)),   # axis x: (0, -sin, cos)
        (1, 30.0, (-0.5, 0.0, np.sqrt(3) / 2)),   # axis y: (-sin, 0, cos)
        (2, 30.0, (-0.5, np.sqrt(3) / 2, 0.0)),   # axis z: (-sin, cos, 0)
        (0, 90.0, (0.0, -1.0, 0.0)),
        (2, 180.0, (0.0, -1.0, 0.0)),
    ],
)
def test_gravity_direction_follows_contract(axis, theta, expected):
    got = gravity_direction(np.array([axis]), np.array([theta]))[0]
    np.testing.assert_allclose(got, expected, atol=1e-15)


def test_unit_vectors_have_requested_angles_and_are_right_handed():
    phi = (89.9, 90.12, 90.05)
    unit = unit_vectors_from_angles(*phi)
    np.testing.assert_allclose(np.linalg.norm(unit, axis=1), 1.0, rtol=1e-15)
    got = [np.degrees(np.arccos(unit[i] @ unit[j])) for i, j in ANGLE_PAIRS]
    np.testing.assert_allclose(got, phi, atol=1e-12)
    assert np.linalg.det(unit) > 0


def test_intrinsic_parameters_ignore_a_common_rotation_or_reflection():
    rng = np.random.default_rng(0)
    resp = unit_vectors_from_angles(89.8, 90.1, 90.2) * np.array([[1660.0], [1670.0], [1675.0]])
    offsets = np.array([10.0, -20.0, 30.0])
    base = intrinsic_from_vectors(resp, offsets)
    rot = rotation_matrix(rng.standard_normal(3), 37.0)
    reflect = np.diag([1.0, -1.0, 1.0])
    np.testing.assert_allclose(intrinsic_from_vectors(resp @ rot.T, offsets), base, rtol=1e-13)
    np.testing.assert_allclose(intrinsic_from_vectors(resp @ reflect, offsets), base, rtol=1e-13)
    np.testing.assert_allclose(base[:3], [1660.0, 1670.0, 1675.0], rtol=1e-14)
    np.testing.assert_allclose(base[3:6], [89.8, 90.1, 90.2], atol=1e-11)
