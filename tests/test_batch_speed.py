"""Issue 16 item 3: the batch's speed-ups keep the values they replace."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
from scipy.stats import chi2

from rotcal.diagnose.fitting import chi2_sf
from rotcal.diagnose.scans import _segment_chi2


def test_chi2_sf_is_scipys_including_below_the_support():
    for x in (-3.0, -1e-17, 0.0, 1e-300, 0.7, 12.5, 400.0, 1e5, np.inf):
        for dof in (1, 2, 7, 30, 215):
            assert chi2_sf(x, dof) == chi2.sf(x, dof)
    assert np.isnan(chi2_sf(np.nan, 3))


def test_segment_chi2_is_each_segments_own_regression():
    """Against an independent least-squares fit per segment: coefficients and
    the chi-square they explain (||projection||^2 of the standardised residuals)."""
    rng = np.random.default_rng(5)
    starts = np.array([0, 40, 140, 400])
    n = 500
    theta = rng.uniform(0, 2 * np.pi, n)
    basis = np.column_stack([np.ones(n), np.sin(3 * theta), np.cos(3 * theta)])
    e = rng.normal(size=n) + 0.3 * basis[:, 1]
    x2, coef = _segment_chi2(e, basis, starts)
    for k, (a, b) in enumerate(zip(starts, np.r_[starts[1:], n])):
        truth = np.linalg.lstsq(basis[a:b], e[a:b], rcond=None)[0]
        np.testing.assert_allclose(coef[k], truth, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(x2[k], np.sum((basis[a:b] @ truth) ** 2), rtol=1e-9)


def test_the_diagnosis_report_imports_matplotlib_only_to_draw():
    code = "import sys, rotcal.report.diagnosis, rotcal.report.certificate, rotcal.run; print('matplotlib' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"
