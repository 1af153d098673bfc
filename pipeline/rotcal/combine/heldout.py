"""Whether a richer model predicts held-out poses better than a simpler one.

A richer model (nine parameters over six, a model with an effect) always
fits the poses it was fitted to at least as well; what earns its place is
predicting a pose it did not see. For each pose k, the prediction error of
the model fitted without it is, for a least-squares fit linearised at its
solution, the PRESS residual (Allen 1974): e_k / (1 - h_kk) for a pose of
one weighted residual, (I - H_kk)^-1 e_k for a pose of several (its block
of the hat matrix H = J (J'J)^-1 J'). Both models' residuals are weighed
alike (the richer model's variances), so that their squared prediction
errors are comparable pose by pose.

"Better by more than chance" is a one-sided paired test (Student's t on
n - 1 degrees of freedom, level ``HELDOUT_LEVEL``) of the per-pose log
ratios d_k = ln(1 + |p_k(simple)|^2) - ln(1 + |p_k(rich)|^2) of the
squared prediction errors (in units of each pose's variance, so 1 is a
pose predicted to its noise). The logarithm because squared prediction
errors are heavy-tailed: on the differences themselves one pose predicted
a thousand times worse makes the test's spread, not its mean (4 of 100
sessions of 16 random poses of a non-orthogonal triad kept the six
parameters although every pose was predicted better by the nine). Poses
scattering beyond their noise (hand placement) count against a model that
fits them by chance, which a test taking the noise as the only error would
not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

HELDOUT_LEVEL = 0.05  # the richer model is preferred when the paired test's one-sided p-value falls below it


@dataclass(frozen=True)
class HeldOut:
    """Both models' leave-one-pose-out prediction: the mean squared
    weighted prediction error of each, the paired t statistic of the log
    ratios, its degrees of freedom and one-sided p-value, and the poses the
    richer model predicts better."""

    simple: float
    rich: float
    t: float
    dof: int
    p_value: float
    wins: int = 0  # poses the richer model predicts better
    ranked: bool = False  # the test is Wilcoxon's signed-rank test (``signed_rank``), ``t`` its statistic W+

    @property
    def better(self) -> bool:
        return self.p_value < HELDOUT_LEVEL

    def text(self, simple: str, rich: str, unit: str = "pose") -> str:
        verdict = "predicts" if self.better else "does not predict"
        n = self.dof + 1
        test = (f"Wilcoxon signed-rank W+ of the log ratios = {self.t:.4g} of {n * (n + 1) // 2}" if self.ranked
                else f"paired t of the log ratios = {self.t:.3g} on {self.dof} dof")
        return (f"left out one {unit} at a time, the {rich} model {verdict} the held-out {unit}s better than the {simple} "
                f"model by more than chance (mean squared weighted prediction error {self.rich:.3g} against {self.simple:.3g}; "
                f"better for {self.wins} of {n} {unit}s; {test}, one-sided p = {self.p_value:.3g}, level {HELDOUT_LEVEL:g})")


def press(residuals: np.ndarray, jac: np.ndarray, size: int = 1) -> np.ndarray:
    """Per pose, the squared norm of its leave-one-out prediction error:
    ``residuals`` (n size,) and ``jac`` (n size, p) weighted, each pose's
    ``size`` rows consecutive."""
    q, _ = np.linalg.qr(jac)
    hat = q @ q.T
    n = residuals.size // size
    blocks = hat.reshape(n, size, n, size)[np.arange(n), :, np.arange(n), :]  # (n, size, size): H_kk
    e = residuals.reshape(n, size, 1)
    held = np.linalg.solve(np.eye(size)[None] - blocks, e)[..., 0]
    return np.einsum("ki,ki->k", held, held)


def compare(simple: np.ndarray, rich: np.ndarray) -> HeldOut:
    """The paired one-sided test of ``rich`` predicting better than
    ``simple`` (each the per-pose squared prediction errors of ``press``)."""
    from scipy.special import stdtr  # here: scipy's import would slow every CLI start

    d = np.log1p(simple) - np.log1p(rich)
    n = d.size
    wins = int(np.sum(d > 0))
    spread = float(np.std(d, ddof=1)) if n > 1 else 0.0
    mean = float(np.mean(d))
    if n < 2 or spread == 0.0:
        t, p = (float("inf"), 0.0) if mean > 0 and n > 1 else (0.0, 1.0)
    else:
        t = mean / (spread / np.sqrt(n))
        p = float(stdtr(n - 1, -t))
    return HeldOut(float(np.mean(simple)), float(np.mean(rich)), t, max(n - 1, 0), p, wins)


def signed_rank(simple: np.ndarray, rich: np.ndarray) -> HeldOut:
    """Wilcoxon's one-sided signed-rank test (exact for up to 50 units
    without ties) of the same log ratios as ``compare``, for units whose
    gains differ by orders of magnitude for a reason (table segments at
    rates a decade apart, where an effect growing with rate gains 500 times
    in the fastest and 5 % in the slowest): the t statistic's spread would
    be made by that spread of sizes, the ranks count how consistently the
    richer model predicts better."""
    from scipy.stats import wilcoxon  # here: scipy.stats's import would slow every CLI start

    d = np.log1p(simple) - np.log1p(rich)
    n = d.size
    wins = int(np.sum(d > 0))
    if n < 2 or not np.any(d):
        w, p = 0.0, 1.0
    else:
        test = wilcoxon(d, alternative="greater")
        w, p = float(test.statistic), float(test.pvalue)
    return HeldOut(float(np.mean(simple)), float(np.mean(rich)), w, max(n - 1, 0), p, wins, ranked=True)
