"""Recordings of the long degenerate run (``scripts/degenerate.py --seed 1``)
that broke the invariant, replayed: each within its uncertainties of the
truth now, and the rounding's covariance of a coarse channel's sine fit
against hand-derived values."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import degenerate_inputs  # noqa: E402


@pytest.mark.parametrize("index, before", [
    (900, "0 Hz: s_w 80.39 u off"),     # four jig positions near one circle: the orthogonal model's fixed angles
    (557, "0 Hz: O_v 35.61 u off"),
    (1272, "0.05 Hz: O_w 13.85 u off"),  # step 200: a channel across the rotation axis, one level throughout
    (1956, "0.5 Hz: phi_vw 6.19 u off"),  # step 1000: a cross-axis sine at a step's edge, rounded to a square wave
])
def test_the_long_runs_violations_hold_now(tmp_path, index, before):
    drawn = degenerate_inputs.draw(np.random.default_rng([1, index]), tmp_path / "ds")
    assert degenerate_inputs.violation(drawn, tmp_path / "out") is None, (drawn.kind, drawn.detail, before)


def test_a_constant_channel_below_the_step_shares_one_rounding_error():
    """Hand-derived: a constant signal without noise rounds to one level;
    its mean's error is uniform over the step (the signal's place in it
    unknown): Delta^2 / 12 in C, whatever the number of samples. A sine
    of 20 counts at a step of 1000 is not known from its samples: A and B
    carry the bound of any rounding error's fundamental, 2 Delta / pi, as a
    rectangular distribution."""
    from rotcal.fit.quantization import rounding_covariance

    theta = np.linspace(0.0, 720.0, 400, endpoint=False)
    step = np.array([1000.0, 1000.0, 1.0])
    coef = np.array([[0.0, 0.0, 0.0], [490.0, 20.0, 0.0], [0.0, 16000.0, 0.0]])
    floor = rounding_covariance(step, coef, theta, np.array([0.0, 0.0, 64.0])).reshape(3, 3)
    assert floor[0, 0] == pytest.approx(1000.0**2 / 12, rel=1e-12)
    assert floor[1, 1] == floor[1, 2] == pytest.approx((2 * 1000.0 / np.pi) ** 2 / 3, rel=1e-12)
    assert not floor[2].any()  # noise of 8 counts at a step of 1: dithered, no floor
