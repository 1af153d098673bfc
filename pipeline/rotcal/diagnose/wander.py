"""Effects that act on the segments' offsets, tested against the offset's
wander.

Some effects move each segment's offset as a whole (``offset_drift``,
``centripetal``, ``axis_tilt``: a trend in time, a shift growing with the
rate squared, a shift per axis; the effects' ``moves_segment_offsets``),
and so does an offset step in every channel (the ``unexplained`` step). So does a slow wander of the sensor's bias (a Gauss-Markov term,
flicker, a random walk), which the sample-level tests, taking the noise as
white within segments, read as a deterministic misfit. Where the fits
measured such a wander (``fit.wander``: the offsets scatter beyond their
fits and beyond the drift, axis and rate pattern these effects would
leave, so white noise with these effects measures none; or
``fit.spectrum``: the residuals' density near zero frequency lies above
white), each selected extension of these effects whose removal changes
the residuals mostly by segment (``SEGMENT_CONSTANT`` of the change's sum
of squares in its segment means) is tested again where the two compete:
the segment means of the residuals without it, c, against its segment
means d, by generalised least squares with the segment means' covariance
under the noise model (``_segment_test``: each fit's u(C)^2, which holds
the density near zero frequency and the wander's floor q, and the floor's
correlation between segments):

    chi^2 = (d^T V^-1 c)^2 / (d^T V^-1 d),  on the extension's parameter count.

Where that is not significant at the diagnosis's false-alarm rate the
wander explains the pattern: the extension is dropped from the model and
its row says so with the wander's size; where it is, the row says the
evidence favours the effect over the wander. Without a measured wander
(white noise) nothing changes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import polars as pl

from rotcal.diagnose.candidates import STEP
from rotcal.diagnose.fitting import ModelFit, chi2_sf, without
from rotcal.diagnose.scans import p_is
from rotcal.model.effects import catalogue
from rotcal.model.physics import CHANNELS

# these effects are constant within a segment (a drift nearly so), but dropping one refits the rest, whose
# readjustment varies within segments: a third of the difference constant marks a segment-level pattern
SEGMENT_CONSTANT = 0.3
# the wander's correlation times tried, as shares of the recording's duration (besides independent offsets)
WANDER_TIMES = (0.03, 0.1, 0.3, 1.0, 3.0, 10.0)


@dataclass(frozen=True, eq=False)
class OffsetNoise:
    """Each fitted segment's offset uncertainty u(C), the wander's floor in
    it and the noise density's ratio to white near zero frequency, per
    channel (``fits`` table columns)."""

    u: dict[int, np.ndarray]
    floor: dict[int, np.ndarray]
    ratio_zero: dict[int, np.ndarray] = field(default_factory=dict)

    @classmethod
    def from_fits(cls, fits: pl.DataFrame) -> OffsetNoise:
        u: dict[int, np.ndarray] = {}
        floor: dict[int, np.ndarray] = {}
        ratio: dict[int, np.ndarray] = {}
        rank = {c: i for i, c in enumerate(CHANNELS)}
        columns = ("segment", "channel", "u_C", "offset_floor", "noise_ratio_zero")
        for seg, ch, u_c, f, f0 in fits.filter(pl.col("status") == "ok").select(columns).iter_rows():
            u.setdefault(seg, np.full(3, np.nan))[rank[ch]] = u_c
            floor.setdefault(seg, np.zeros(3))[rank[ch]] = f if f is not None and np.isfinite(f) else 0.0
            ratio.setdefault(seg, np.ones(3))[rank[ch]] = f0 if f0 is not None and np.isfinite(f0) else 1.0
        return cls(u, floor, ratio)

    @property
    def wanders(self) -> bool:
        """Whether the fits measured noise beyond white at the offsets'
        frequencies: a floor between segments, or a density near zero
        frequency above white within them."""
        return (any(np.any(f > 0) for f in self.floor.values())
                or any(np.any(f > 1) for f in self.ratio_zero.values()))

    def size(self) -> str:
        """The wander's size per channel: the largest floor of its segments,
        and the largest density ratio near zero frequency where above 1."""
        top = np.max(np.array(list(self.floor.values())), axis=0)
        text = "largest floor " + ", ".join(f"{c} {v:.3g}" for c, v in zip(CHANNELS, top))
        ratio = np.max(np.array(list(self.ratio_zero.values())), axis=0) if self.ratio_zero else np.ones(3)
        if np.any(ratio > 1):
            text += "; density near zero frequency " + ", ".join(f"{c} {v:.3g}" for c, v in zip(CHANNELS, ratio)) + " times white"
        return text


def against_wander(final: ModelFit, noise: OffsetNoise, alpha: float, output_unit: str) -> tuple[ModelFit, dict[str, str]]:
    """The model with the offset effects the wander explains dropped, and
    per effect the sentence its diagnosis row adds (module docstring)."""
    texts: dict[str, str] = {}
    if not noise.wanders:
        return final, texts
    rivals = {e.name for e in catalogue() if e.moves_segment_offsets}
    # an offset step in every channel moves the offsets of the segments after it alike
    for cand in [c for c in final.active if c.effect in rivals or c == STEP]:
        reduced = without(final, (cand,))
        stat, constant = _segment_test(final, reduced, noise, cand == STEP)
        if stat is None or constant < SEGMENT_CONSTANT:
            continue
        k = len(cand.names)
        # the step's time was chosen where it fits best: Bonferroni over the segment boundaries it could take
        scanned = max(1, len(np.unique(final.obs.segment)) - 1) if cand == STEP else 1
        p = min(1.0, chi2_sf(stat, k) * scanned)
        size = f"the offsets wander ({noise.size()}; floors in {output_unit})"
        if p >= alpha:
            final = reduced
            text = (f"{cand.key} set aside: {size}, and that wander explains its pattern in the segments' offsets "
                    f"(chi-square {stat:.1f} on {k} against the wander, {p_is(p)})")
        else:
            text = (f"for {cand.key} the evidence favours the effect over the wander ({size}; against the wander "
                    f"chi-square {stat:.1f} on {k}, {p_is(p)})")
        texts[cand.effect] = f"{texts[cand.effect]}; {text}" if cand.effect in texts else text
    return final, texts


def _segment_test(final: ModelFit, reduced: ModelFit, noise: OffsetNoise,
                  refloor: bool = False) -> tuple[float | None, float]:
    """(chi^2 of the extension's segment means against the noise model,
    the share of its fitted part that is constant within segments). The
    segment means' covariance is V = diag(u(C)^2) + q_i q_j (rho_ij - delta_ij),
    q the wander's floor and rho_ij = exp(-|t_i - t_j| / T) the correlation
    of a wander of correlation time T (a Gauss-Markov term; T = 0:
    independent offsets). The fits measure q, not T: the statistic is the
    least over ``WANDER_TIMES`` of the recording's duration, the correlation
    time that explains the pattern best (a slow wander moves neighbouring
    segments alike, as a drift or a step would). ``refloor``: the fits'
    floor leaves out the catalogue effects' patterns, not an offset step's,
    so a step would be tested against the wander it makes itself: the
    likelihood ratio of the step with q and T fitted under both hypotheses
    instead (``_likelihood_ratio``)."""
    seg = final.obs.segment
    ids, idx = np.unique(seg, return_inverse=True)
    if not all(int(s) in noise.u for s in ids):
        return None, 0.0
    use = final.use & reduced.use
    before = np.where(use, reduced.residuals, 0.0)
    part = np.where(use, reduced.residuals - final.residuals, 0.0)
    count = np.stack([np.bincount(idx, use[:, r], ids.size) for r in range(3)], axis=1)
    on = count > 0
    safe = np.where(on, count, 1)
    c = np.stack([np.bincount(idx, before[:, r], ids.size) for r in range(3)], axis=1) / safe
    d = np.stack([np.bincount(idx, part[:, r], ids.size) for r in range(3)], axis=1) / safe
    total = float(np.sum(part**2))
    if total <= 0:
        return None, 0.0
    constant = float(np.sum(count * d**2)) / total
    var = np.array([noise.u[int(s)] for s in ids]) ** 2
    floor = np.array([noise.floor[int(s)] for s in ids])
    t = final.obs.motion.t_s
    centre = np.bincount(idx, t, ids.size) / np.bincount(idx, minlength=ids.size)
    lag = np.abs(centre[:, None] - centre[None, :])
    duration = float(t.max() - t.min()) if t.size else 0.0
    if refloor:
        within = np.maximum(var - floor**2, 1e-300)
        ok = on & np.isfinite(within)
        rate = np.zeros(ids.size, int)
        rate[idx] = final.obs.rate_idx
        return _likelihood_ratio(c, d, within, ok, lag, centre - centre.min(), duration, rate), constant
    stats = []
    for share in (0.0,) + WANDER_TIMES:
        rho = np.eye(ids.size) if share == 0.0 or duration <= 0 else np.exp(-lag / (share * duration))
        num, info = 0.0, 0.0
        for r in range(3):
            ok = on[:, r] & np.isfinite(var[:, r]) & (var[:, r] > 0)
            if not ok.any():
                continue
            q = floor[ok, r]
            v = np.diag(var[ok, r]) + np.outer(q, q) * (rho[np.ix_(ok, ok)] - np.eye(int(ok.sum())))
            w = np.linalg.solve(v, d[ok, r])
            num += float(w @ c[ok, r])
            info += float(w @ d[ok, r])
        if info > 0:
            stats.append(num**2 / info)
    if not stats:
        return None, constant
    return min(stats), constant


def _log_likelihood(m: np.ndarray, x: np.ndarray | None, v: np.ndarray) -> float:
    """Gaussian log-likelihood (without constants) of ``m`` ~ N(x beta, v), beta at its GLS value."""
    chol = np.linalg.cholesky(v)
    white = np.linalg.solve(chol, m)
    rss = float(white @ white)
    if x is not None:
        wx = np.linalg.solve(chol, x)
        info = float(wx @ wx)
        if info > 0:
            rss -= float(wx @ white) ** 2 / info
    return -0.5 * (2 * float(np.sum(np.log(np.diag(chol)))) + rss)


def _likelihood_ratio(c: np.ndarray, d: np.ndarray, within: np.ndarray, ok: np.ndarray, lag: np.ndarray,
                      start: np.ndarray, duration: float, rate: np.ndarray) -> float:
    """2 ln LR of the pattern ``d`` (one free size per channel) in the
    segment means ``c``, each hypothesis with its own wander: V = diag(
    ``within``) + q^2 exp(-lag / T), q on a grid to three times the means'
    spread and T over ``WANDER_TIMES`` of ``duration`` (and independent),
    or a random walk, q^2 min(t_i, t_j) / duration (``start``: the segments'
    times from the first), both fitted by maximum likelihood, summed over
    channels. The means are residuals of a model with an offset per rate
    (``rate``: each segment's), so the likelihoods are those of the
    contrasts free of them (restricted maximum likelihood, Patterson &
    Thompson 1971): everything projected on the complement of the rates'
    indicators."""
    total = 0.0
    shapes = [np.eye(lag.shape[0])] + ([np.exp(-lag / (share * duration)) for share in WANDER_TIMES] if duration > 0 else [])
    if duration > 0:   # a random walk from the first segment: Cov = q^2 min(t_i, t_j) / duration
        shapes.append(np.minimum(start[:, None], start[None, :]) / duration)
    for r in range(3):
        on = ok[:, r]
        if on.sum() < 3:
            continue
        rates = np.unique(rate[on])
        if on.sum() <= rates.size + 1:
            continue
        indicators = (rate[on][:, None] == rates[None, :]).astype(float)
        basis = np.linalg.svd(indicators, full_matrices=True)[0][:, rates.size:]   # the contrasts
        m, x, w = basis.T @ c[on, r], basis.T @ d[on, r], np.diag(within[on, r])
        spread = float(np.sqrt(np.mean(m**2)))
        best = [-np.inf, -np.inf]
        for q in np.r_[0.0, spread * np.geomspace(0.03, 3.0, 12)]:
            for rho in shapes:
                v = basis.T @ (w + q**2 * rho[np.ix_(on, on)]) @ basis
                for h, design in enumerate((None, x)):
                    best[h] = max(best[h], _log_likelihood(m, design, v))
        total += max(0.0, 2 * (best[1] - best[0]))
    return total

