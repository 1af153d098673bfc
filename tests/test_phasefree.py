"""Rotation segments without a phase reference: the joint solve of the
unknown angles against closed-form truth, against the labelled reduction of
the same coefficients, and its coverage (issue 5)."""

import numpy as np
import pytest

from rotcal.combine.labelled import SegmentCoefficients, combine_rate
from rotcal.combine.phasefree import PhaseSegment, solve_phase_free
from rotcal.model.physics import AXES, COS_COMPONENT, SIN_COMPONENT, intrinsic_from_vectors, rotation_matrix, unit_vectors_from_angles
from rotcal.model.results import Failure

G = 9.80101


def _dut(rng):
    unit = unit_vectors_from_angles(*(90 + rng.uniform(-0.15, 0.15, 3))) @ rotation_matrix(rng.normal(size=3), 3.0).T
    return unit * (1669 + rng.uniform(-4, 4, 3))[:, None], rng.uniform(-600, 600, 3)


def _labelled_coef(resp, offsets, axis):
    """Coefficients against the table angle (docs/conventions.md): A = -g r_a, B = g r_b, C = O."""
    s = AXES.index(axis)
    return np.column_stack([offsets, -G * resp[:, SIN_COMPONENT[s]], G * resp[:, COS_COMPONENT[s]]]).ravel()


def _own_phase(coef, theta0_deg, reverse):
    """The same segment against phi, theta = theta0 +- phi."""
    c = coef.reshape(3, 3).copy()
    a, b = c[:, 1].copy(), c[:, 2].copy()
    th = np.deg2rad(theta0_deg)
    # R = A sin(theta0 +- phi) + B cos(theta0 +- phi)
    sign = -1.0 if reverse else 1.0
    c[:, 1] = sign * (a * np.cos(th) - b * np.sin(th))
    c[:, 2] = a * np.sin(th) + b * np.cos(th)
    return c.ravel()


def _noise_cov(rng, n=4200, sigma=8.0):
    """Covariance of a sine fit's (C, A, B) with white noise over whole turns."""
    block = np.diag([1.0, 2.0, 2.0]) * sigma**2 / n
    return np.kron(np.eye(3), block)


def test_noise_free_unknown_angles_and_reflections_give_the_truth():
    rng = np.random.default_rng(1)
    resp, offsets = _dut(rng)
    truth = intrinsic_from_vectors(resp, offsets)
    segs = [PhaseSegment(k, axis, _own_phase(_labelled_coef(resp, offsets, axis), rng.uniform(0, 360), rng.random() < 0.5),
                         np.eye(9) * 1e-12) for k, axis in enumerate(AXES)]
    fit = solve_phase_free(0.1, segs, G, 0.0)
    np.testing.assert_allclose(fit.result.value, truth, rtol=1e-10, atol=1e-8)
    assert fit.chi2 < 1e-6
    # no continuous freedom is left, and the axes' signs follow the DUT's alignment: the table frame
    np.testing.assert_allclose(fit.result.responsivity, resp, rtol=1e-10, atol=1e-8)


def test_matches_the_labelled_combination_and_covers_the_truth():
    """Same noisy coefficients, once with their table angles (combine) and
    once turned by unknown angles (phase-free): the results agree to a small
    fraction of u; over 150 DUTs the phase-free z-scores have unit spread."""
    rng = np.random.default_rng(2)
    z, diff = [], []
    for _ in range(150):
        resp, offsets = _dut(rng)
        cov = _noise_cov(rng)
        chol = np.linalg.cholesky(cov)
        noisy = {axis: _labelled_coef(resp, offsets, axis) + chol @ rng.normal(size=9) for axis in AXES}
        labelled = combine_rate(0.1, [SegmentCoefficients(k, a, noisy[a], cov) for k, a in enumerate(AXES)], G, 0.0)
        turned = []
        for k, a in enumerate(AXES):
            th, rev = rng.uniform(0, 360), rng.random() < 0.5
            # the covariance turns with the coefficients (here isotropic in A, B: unchanged)
            turned.append(PhaseSegment(k, a, _own_phase(noisy[a], th, rev), cov))
        fit = solve_phase_free(0.1, turned, G, 0.0)
        diff.append((fit.result.value - labelled.value) / labelled.std_uncertainty)
        z.append((fit.result.value - intrinsic_from_vectors(resp, offsets)) / fit.result.std_uncertainty)
    assert np.abs(diff).max() < 0.1
    z = np.array(z)
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.15)
    assert np.abs(z.mean(axis=0)).max() < 0.3


def test_segments_with_a_table_angle_fix_the_phase_and_the_signs():
    rng = np.random.default_rng(3)
    resp, offsets = _dut(rng)
    cov = _noise_cov(rng)
    chol = np.linalg.cholesky(cov)
    coef = {a: _labelled_coef(resp, offsets, a) + chol @ rng.normal(size=9) for a in AXES}
    segs = [PhaseSegment(0, "x", coef["x"], cov, fixed=True), PhaseSegment(1, "y", coef["y"], cov, fixed=True),
            PhaseSegment(2, "z", _own_phase(coef["z"], 123.0, False), cov)]
    fit = solve_phase_free(0.05, segs, G, 0.0)
    assert np.isnan(fit.theta_deg[:2]).all() and fit.theta_deg[2] == pytest.approx(123.0, abs=0.05)
    # the components are those of the table frame (signs fixed by the labelled segments)
    np.testing.assert_allclose(fit.result.responsivity, resp, atol=0.05)


def test_a_missing_axis_is_a_failure_with_its_reason():
    rng = np.random.default_rng(4)
    resp, offsets = _dut(rng)
    segs = [PhaseSegment(k, a, _labelled_coef(resp, offsets, a), np.eye(9)) for k, a in enumerate(("x", "y"))]
    out = solve_phase_free(0.05, segs, G, 0.0)
    assert isinstance(out, Failure)
    # x and y measure every component once: the reason names what is missing (it read "leave  unmeasured")
    assert out.reason == ("segments about axes x, y only: rotations without a table angle need all three axes "
                          "to solve their unknown starting angles")
    alone = solve_phase_free(0.05, segs[:1], G, 0.0)
    assert alone.reason == "segments about axes x leave rho_ux, rho_vx, rho_wx unmeasured"
