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
        p = chi2_sf(stat, k)
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
    segments alike, as a drift or a step would). ``refloor``: q measured
    again from the segment means of ``final``'s residuals (the fits' floor
    leaves out the catalogue effects' patterns, not an offset step's, so a
    step would be tested against the wander it makes itself)."""
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
    if refloor:
        var, floor = _refloored(c - d, var, floor, on, final.layout.n_rates)
    t = final.obs.motion.t_s
    centre = np.bincount(idx, t, ids.size) / np.bincount(idx, minlength=ids.size)
    lag = np.abs(centre[:, None] - centre[None, :])
    duration = float(t.max() - t.min()) if t.size else 0.0
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


def _refloored(means: np.ndarray, var: np.ndarray, floor: np.ndarray, on: np.ndarray,
               n_rates: int) -> tuple[np.ndarray, np.ndarray]:
    """(u(C)^2, floor) per segment and channel with the floor measured from
    the segment ``means`` of a model's residuals (DerSimonian & Laird 1986,
    the model's offsets per rate taken off the degrees of freedom) in place
    of the fits'."""
    within = np.maximum(var - floor**2, 1e-300)
    out = np.zeros(3)
    for r in range(3):
        ok = on[:, r] & np.isfinite(within[:, r])
        w = 1.0 / within[ok, r]
        if w.size <= n_rates + 1:
            continue
        m = means[ok, r]
        q = float(np.sum(w * (m - np.sum(w * m) / np.sum(w)) ** 2))
        out[r] = np.sqrt(max(0.0, (q - (w.size - n_rates)) / (np.sum(w) - np.sum(w**2) / np.sum(w))))
    floor = np.broadcast_to(out, floor.shape).copy()
    return within + floor**2, floor
