"""The result records (issue 12): every reduction builds its intrinsic
results through the one constructor, so g_local's uncertainty and the
budget's input groups are always set and add up to the covariance; one
failure record; a reduction record that leaves out the rates another
answers for."""

import numpy as np
import polars as pl
import pytest

from rotcal.combine.labelled import SegmentCoefficients, combine_rate
from rotcal.combine.multiposition import orientation_free
from rotcal.combine.phasefree import PhaseSegment, solve_phase_free
from rotcal.combine.poses import reference_fit
from rotcal.model.physics import AXES, CHANNELS, COS_COMPONENT, SIN_COMPONENT, rotation_matrix, unit_vectors_from_angles
from rotcal.model.results import WHOLE_FIT, Failure, IntrinsicResult, Reduction, Table

G, U_G = 9.80101, 2e-5


def _dut(rng):
    unit = unit_vectors_from_angles(*(90 + rng.uniform(-0.15, 0.15, 3))) @ rotation_matrix(rng.normal(size=3), 3.0).T
    return unit * (1669 + rng.uniform(-4, 4, 3))[:, None], rng.uniform(-600, 600, 3)


def _segments(rng, resp, offsets, own_phase):
    """Noisy coefficients of one rotation per axis (docs/conventions.md), turned by an unknown angle when ``own_phase``."""
    cov = np.kron(np.eye(3), np.diag([1.0, 2.0, 2.0]) * 64.0 / 4200)
    out = []
    for k, axis in enumerate(AXES):
        s = AXES.index(axis)
        c = np.column_stack([offsets, -G * resp[:, SIN_COMPONENT[s]], G * resp[:, COS_COMPONENT[s]]])
        c = (c.ravel() + rng.multivariate_normal(np.zeros(9), cov)).reshape(3, 3)
        if own_phase:
            th = rng.uniform(0, 2 * np.pi)
            c[:, 1], c[:, 2] = c[:, 1] * np.cos(th) - c[:, 2] * np.sin(th), c[:, 1] * np.sin(th) + c[:, 2] * np.cos(th)
        out.append((k, axis, c.ravel(), cov))
    return out


def _poses(rng, resp, offsets, n=16):
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    cov = np.broadcast_to(np.eye(3) * 0.05, (n, 3, 3))
    m = offsets + G * d @ resp.T + rng.normal(0, np.sqrt(0.05), (n, 3))
    return pl.DataFrame({"pose": np.arange(n), **{f"mean_{c}": m[:, r] for r, c in enumerate(CHANNELS)},
                         "cov_mean": cov.reshape(n, 9).tolist(), **{f"ref_{s}": d[:, i] for i, s in enumerate("xyz")}})


def _every_reduction():
    rng = np.random.default_rng(12)
    resp, offsets = _dut(rng)
    labelled = [SegmentCoefficients(k, a, c, cov, 4000) for k, a, c, cov in _segments(rng, resp, offsets, False)]
    turned = [PhaseSegment(k, a, c, cov, dof=4000) for k, a, c, cov in _segments(rng, resp, offsets, True)]
    poses = _poses(rng, resp, offsets)
    return {"labelled": combine_rate(0.5, labelled, G, U_G), "phase-free": solve_phase_free(0.5, turned, G, U_G).result,
            "orientation-free": orientation_free(poses, G, U_G).result, "reference": reference_fit(poses, G, U_G).result}


@pytest.mark.parametrize("name", ["labelled", "phase-free", "orientation-free", "reference"])
def test_every_reduction_sets_g_uncertainty_and_a_budget_that_adds_up(name):
    res = _every_reduction()[name]
    assert isinstance(res, IntrinsicResult)
    assert res.g_uncertainty == U_G
    labels = [inp.label for inp in res.inputs]
    assert labels[-1] == "g_local" and len(labels) >= 2 and set(labels) == set(res.budget)
    # the input groups are independent: their contributions add up to the combined variance
    np.testing.assert_allclose(sum(res.budget.values()), np.diag(res.cov), rtol=1e-9)
    assert np.all(res.budget["g_local"][:3] > 0) and np.all(res.budget["g_local"][3:] == 0)
    whole = [inp for inp in res.inputs if inp.source == WHOLE_FIT]
    # a reduction without a per-segment breakdown says so (source WHOLE_FIT), with its degrees of freedom
    assert bool(whole) == (name in ("orientation-free", "reference"))
    assert all(inp.dof > 0 for inp in res.inputs)


def test_the_constructor_refuses_a_result_without_noise_inputs():
    with pytest.raises(ValueError, match="noise input groups"):
        IntrinsicResult.from_state(0.0, np.r_[np.eye(3).ravel() * G, np.zeros(3)], np.eye(12), G, 0.0, [])


def test_a_reduction_without_the_rates_another_answers_for():
    res = _every_reduction()["labelled"]
    table = Table("components", pl.DataFrame({"rate_hz": [0.0, 0.5, 0.5], "value": [1.0, 2.0, 3.0]}))
    reduction = Reduction("table", (res,), (Failure(0.0, "unmeasured"),), (table,), ("w",))
    assert reduction.rates == {0.0, 0.5}
    assert reduction.without(frozenset({1.0})) is reduction
    rest = reduction.without(frozenset({0.5}))
    assert rest.results == () and rest.failures == reduction.failures and rest.warnings == ("w",)
    assert rest.tables[0].data["value"].to_list() == [1.0]
    assert reduction.without(frozenset({0.0})).tables[0].data["rate_hz"].to_list() == [0.5, 0.5]
