"""The noise model of residuals that a deterministic misfit dominates (a
rate error left unmodelled: the Allan variance peaks at the misfit's period
and falls two orders beyond it) is fitted or refused with a reason, never
a traceback. The Allan variance is the one a default-plan recording with
``rate_error=-3e-5`` (seed 40) gave its u channel."""

from __future__ import annotations

import numpy as np

from rotcal.noise.allan import AllanVariance
from rotcal.noise.model import fit_channel

TAU = 0.06 * 2.0 ** np.arange(12)
AVAR = np.array([8.13282329e+01, 1.00662757e+02, 2.72214725e+02, 7.78630421e+02, 8.90744289e+02, 2.73400523e+01,
                 4.78010654e+01, 1.38986618e+01, 5.08062352e+00, 1.19162689e+00, 2.31252970e-01, 1.44025510e-01])
EDF = np.array([7.32143984e+01, 2.68367347e+04, 1.33041715e+04, 6.55669834e+03, 4.86862385e+03, 2.33509847e+03,
                9.41342213e+02, 5.66452587e+02, 2.71248442e+02, 1.23631933e+02, 4.98219161e+01, 1.29166982e+01])


def test_a_misfit_dominated_allan_variance_gives_a_model_or_a_reason() -> None:
    av = AllanVariance(TAU, AVAR, np.ones_like(TAU), EDF)
    noise = fit_channel("u", av, 0.06, "count")
    if noise.reason:
        assert "misfit" in noise.reason
    else:
        assert noise.terms and all(np.isfinite(t.value) and np.isfinite(t.u) for t in noise.terms)
