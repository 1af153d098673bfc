"""Measured rotation rates against the nominal ones: the logger's clock.

A logger clock that runs fast by d stamps every second as 1 + d seconds, so
every rate it measures looks slow by the same factor:
f_measured = f_nominal / (1 + d). Each segment with a nominal rate (its
label, or the nearest of ``[plan] rates_hz``) gives d_k = f_nominal /
f_measured - 1 with the uncertainty of its measured rate; their
inverse-variance weighted mean is the drift, its uncertainty scaled by the
Birge ratio when the segments scatter more than they should. The drift is
corrected when it is significant and the segments agree on it (one clock
factor); a table whose rate is off by the same factor looks exactly the
same, and the two cannot be told apart without an independent reference.
Without nominal rates, measured rates within ``CLASS_WIDTH`` of each other
are one rate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import chdtrc

PLAN_MATCH = 0.02         # a measured rate within this fraction of a nominal one is that rate
CLASS_WIDTH = 0.01        # measured rates within this fraction of each other form one rate
DRIFT_CONSISTENCY = 1e-3  # chi-square p-value below which the segments do not share one clock factor


@dataclass(frozen=True)
class ClockDrift:
    """The drift d (fraction, logger fast when positive), its standard
    uncertainty, the chi-square of the segments about it and their number."""

    drift: float
    u_drift: float
    chi2: float
    n: int

    @property
    def consistent(self) -> bool:
        return self.n < 2 or chdtrc(self.n - 1, self.chi2) >= DRIFT_CONSISTENCY

    @property
    def detected(self) -> bool:
        return self.n > 0 and self.consistent and abs(self.drift) > 3 * self.u_drift

    @property
    def factor(self) -> float:
        """What the measured rates are multiplied by to be on the table's clock."""
        return 1.0 + self.drift if self.detected else 1.0

    def finding(self, dataset: str) -> dict:
        """The ``clock_drift`` row of the time-base table."""
        row = {"dataset": dataset, "capture": "", "check": "clock_drift", "unit": "ppm", "detected": self.detected}
        if self.n == 0:
            return {**row, "value": None, "std_uncertainty": None, "action": "none",
                    "evidence": "no nominal rates (segment labels or [plan] rates_hz): the logger clock cannot be "
                                "compared with the table"}
        evidence = (f"{self.n} rotation segments measure rates {self.drift * 1e6:.4g} ppm slow against the nominal "
                    f"ones (chi-square {self.chi2:.3g} on {max(self.n - 1, 0)} degrees of freedom): the logger "
                    f"clock runs fast by that much against the table (or the table slow)")
        if not self.consistent:
            evidence += "; the segments disagree, so this is not one clock factor"
        return {**row, "value": self.drift * 1e6, "std_uncertainty": self.u_drift * 1e6,
                "action": "corrected: measured rates multiplied by 1 + drift" if self.detected else "none",
                "evidence": evidence}

    def warnings(self) -> list[str]:
        if self.n and not self.consistent:
            return [f"the measured rates are not off from the nominal ones by one common factor (chi-square "
                    f"{self.chi2:.3g} on {self.n - 1} degrees of freedom): rates kept as measured"]
        if self.detected:
            return [f"logger clock drift {self.drift * 1e6:.4g} +- {self.u_drift * 1e6:.2g} ppm against the table: "
                    "rates corrected"]
        return []


def nominal_rate(rate_hz: float, plan_rates: tuple[float, ...]) -> float | None:
    """The plan rate ``rate_hz`` matches (within PLAN_MATCH), or None."""
    if not plan_rates:
        return None
    plan = np.abs(np.asarray(plan_rates, float))
    k = int(np.argmin(np.abs(np.log(plan / rate_hz))))
    return float(plan[k]) if abs(plan[k] / rate_hz - 1.0) <= PLAN_MATCH else None


def clock_drift(measured_hz: np.ndarray, u_hz: np.ndarray, nominal_hz: np.ndarray) -> ClockDrift:
    """The drift from the segments with a nominal rate (NaN where none)."""
    use = np.isfinite(nominal_hz) & np.isfinite(measured_hz)
    if not use.any():
        return ClockDrift(float("nan"), float("nan"), float("nan"), 0)
    f, nominal = measured_hz[use], np.abs(nominal_hz[use])
    d = nominal / f - 1.0
    w = 1.0 / np.maximum(nominal * u_hz[use] / f**2, 1e-300) ** 2
    mean = float(np.sum(w * d) / np.sum(w))
    chi2 = float(np.sum(w * (d - mean) ** 2))
    birge = np.sqrt(chi2 / (d.size - 1)) if d.size > 1 else 1.0
    return ClockDrift(mean, float(max(birge, 1.0) / np.sqrt(np.sum(w))), chi2, int(d.size))


def rate_classes(rates_hz: np.ndarray) -> np.ndarray:
    """Each rate replaced by its class mean: sorted rates within CLASS_WIDTH
    of their neighbour are one rate."""
    if rates_hz.size == 0:
        return rates_hz.copy()
    order = np.argsort(rates_hz)
    r = rates_hz[order]
    cls = np.r_[0, np.cumsum(np.diff(r) > CLASS_WIDTH * r[1:])]
    out = np.empty_like(rates_hz)
    out[order] = (np.bincount(cls, r) / np.bincount(cls))[cls]
    return out
