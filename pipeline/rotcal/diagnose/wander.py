"""Effects that act on the segments' offsets, tested against the offset's
wander.

Some effects move each segment's offset as a whole (``offset_drift``,
``centripetal``, ``axis_tilt``: a trend in time, a shift growing with the
rate squared, a shift per axis; the effects' ``moves_segment_offsets``),
and so does an offset step in every channel (the ``unexplained`` step).
So does a slow wander of the sensor's bias (a Gauss-Markov term,
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
means d, with the rates' offsets and the other selected offset effects
free (their patterns in the segment means, ``offset_slopes``), by the
restricted likelihood ratio of d's pattern in c (``_likelihood_ratio``)
under the segment means' covariance

    V = diag(each fit's own variance) + q^2 S,

the wander's size q and shape S (independent offsets, Gauss-Markov
correlation times, a random walk from the record's start, IEEE Std 952
Var = K^2 t, over the segments' windows) fitted under both hypotheses, on
the extension's parameter count, Bonferroni over the offset patterns the
selection scored (a step: over the segment boundaries its time could
take). The fits' own floor is not taken as given: it is sized about one
common offset, so it holds the effect's own pattern (an axis tilt's shift
of its axis's segments made a floor of 90 counts, which then explained
the tilt).

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

from rotcal.diagnose.candidates import STEP, Candidate
from rotcal.diagnose.fitting import ModelFit, chi2_sf, without
from rotcal.diagnose.model import predict
from rotcal.diagnose.scans import p_is
from rotcal.model.effects import catalogue
from rotcal.model.physics import CHANNELS
from rotcal.noise.means import NoiseProcess, window_mean_covariance

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
    random_walk: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @classmethod
    def from_fits(cls, fits: pl.DataFrame, random_walk: tuple[float, ...] = ()) -> OffsetNoise:
        """From the ``fits`` table, with the noise model's random walk K per
        channel (``rotcal.noise``; none where not given)."""
        u: dict[int, np.ndarray] = {}
        floor: dict[int, np.ndarray] = {}
        ratio: dict[int, np.ndarray] = {}
        rank = {c: i for i, c in enumerate(CHANNELS)}
        columns = ("segment", "channel", "u_C", "offset_floor", "noise_ratio_zero")
        for seg, ch, u_c, f, f0 in fits.filter(pl.col("status") == "ok").select(columns).iter_rows():
            u.setdefault(seg, np.full(3, np.nan))[rank[ch]] = u_c
            floor.setdefault(seg, np.zeros(3))[rank[ch]] = f if f is not None and np.isfinite(f) else 0.0
            ratio.setdefault(seg, np.ones(3))[rank[ch]] = f0 if f0 is not None and np.isfinite(f0) else 1.0
        return cls(u, floor, ratio, np.array(random_walk, float) if len(random_walk) == 3 else np.zeros(3))

    @property
    def wanders(self) -> bool:
        """Whether the fits measured noise beyond white at the offsets'
        frequencies: a floor between segments, or a density near zero
        frequency above white within them."""
        return (any(np.any(f > 0) for f in self.floor.values())
                or any(np.any(f > 1) for f in self.ratio_zero.values()))

    def size(self, unit: str) -> str:
        """The wander's size per channel: the largest floor of its segments,
        the largest density ratio near zero frequency where above 1 and the
        noise model's random walk where it has one."""
        top = np.max(np.array(list(self.floor.values())), axis=0)
        text = "largest floor " + ", ".join(f"{c} {v:.3g}" for c, v in zip(CHANNELS, top)) + f" {unit}"
        ratio = np.max(np.array(list(self.ratio_zero.values())), axis=0) if self.ratio_zero else np.ones(3)
        if np.any(ratio > 1):
            text += "; density near zero frequency " + ", ".join(f"{c} {v:.3g}" for c, v in zip(CHANNELS, ratio)) + " times white"
        if np.any(self.random_walk > 0):
            text += ("; the noise model's random walk K " + ", ".join(f"{c} {k:.2g}" for c, k in zip(CHANNELS, self.random_walk))
                     + f" {unit}/sqrt(s)")
        return text


def against_wander(final: ModelFit, noise: OffsetNoise, alpha: float, output_unit: str) -> tuple[ModelFit, dict[str, str]]:
    """The model with the offset effects the wander explains dropped, and
    per effect the sentence its diagnosis row adds (module docstring)."""
    texts: dict[str, str] = {}
    if not noise.wanders:
        return final, texts
    rivals = {e.name for e in catalogue() if e.moves_segment_offsets}
    # an offset step in every channel moves the offsets of the segments after it alike
    slopes = offset_slopes(final, rivals)
    for cand in [c for c in final.active if c.effect in rivals or c == STEP]:
        reduced = without(final, (cand,))
        test = segment_test(final, reduced, cand, noise, slopes)
        if test is None or test.constant < SEGMENT_CONSTANT:
            continue
        k = len(cand.names)
        # the step's time was chosen where it fits best: Bonferroni over the segment boundaries it could take;
        # an effect was chosen among every offset pattern the selection scored
        patterns = sum(c.effect in rivals for c in final.layout.candidates)
        scanned = max(1, len(np.unique(final.obs.segment)) - 1) if cand == STEP else max(1, patterns)
        p = min(1.0, chi2_sf(test.stat, k) * scanned)
        size = f"the offsets wander ({noise.size(output_unit)}"
        fitted = ", ".join(f"{c} {w.text(output_unit)}" for c, w in zip(CHANNELS, test.wander) if w is not None)
        size += f"; fitted without it: {fitted})" if fitted else ")"
        if p >= alpha:
            final = reduced
            slopes = offset_slopes(final, rivals)
            text = (f"{cand.key} set aside: {size}, and that wander explains its pattern in the segments' offsets "
                    f"(chi-square {test.stat:.1f} on {k} against the wander, {p_is(p)})")
        else:
            text = (f"for {cand.key} the evidence favours the effect over the wander ({size}; against the wander "
                    f"chi-square {test.stat:.1f} on {k}, {p_is(p)})")
        texts[cand.effect] = f"{texts[cand.effect]}; {text}" if cand.effect in texts else text
    return final, texts


@dataclass(frozen=True)
class WanderFit:
    """A channel's wander of the segment offsets as fitted under the null:
    sd ``q`` (output units) and correlation time ``tau_s`` (0: independent
    offsets; inf: a random walk, q its sd over the record)."""

    q: float
    tau_s: float
    duration_s: float

    def text(self, unit: str) -> str:
        if self.q == 0:
            return "none"
        if np.isinf(self.tau_s):   # IEEE Std 952 random walk: Var = K^2 t
            return f"a random walk of K = {self.q / np.sqrt(self.duration_s):.2g} {unit}/sqrt(s)"
        if self.tau_s == 0:
            return f"{self.q:.2g} {unit} independent per segment"
        return f"{self.q:.2g} {unit} over {self.tau_s:.3g} s"


@dataclass(frozen=True)
class WanderTest:
    """The test of one extension's segment pattern against the offsets'
    wander: its chi-square (2 ln LR for the step), the share of its fitted
    part constant within segments, and for the step the wander fitted
    without it, per channel (``WanderFit``)."""

    stat: float
    constant: float
    wander: tuple[WanderFit | None, ...]


def _segment_means(final: ModelFit, reduced: ModelFit, ids: np.ndarray, idx: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(c, d, samples per segment and channel, the share of d's sum of
    squares in its segment means): c the segment means of the residuals
    without the extension, d those of its fitted part."""
    use = final.use & reduced.use
    before = np.where(use, reduced.residuals, 0.0)
    part = np.where(use, reduced.residuals - final.residuals, 0.0)
    count = np.stack([np.bincount(idx, use[:, r], ids.size) for r in range(3)], axis=1)
    safe = np.where(count > 0, count, 1)
    c = np.stack([np.bincount(idx, before[:, r], ids.size) for r in range(3)], axis=1) / safe
    d = np.stack([np.bincount(idx, part[:, r], ids.size) for r in range(3)], axis=1) / safe
    total = float(np.sum(part**2))
    return c, d, count, (float(np.sum(count * d**2)) / total if total > 0 else 0.0)


def offset_slopes(final: ModelFit, rivals: set[str]) -> dict[str, np.ndarray]:
    """Per selected offset effect (and the step), the segment means
    (segments, parameters, channels) of the model's change along each of
    its parameters (one standard uncertainty's step): the patterns it gives
    the offsets, which the other extensions' tests leave free."""
    ids, idx = np.unique(final.obs.segment, return_inverse=True)
    count = np.stack([np.bincount(idx, final.use[:, r], ids.size) for r in range(3)], axis=1)
    safe = np.where(count > 0, count, 1)
    cov = np.diag(final.covariance())
    base = predict(final.obs, final.beta, final.layout, final.active, final.clip, final.structure)
    out = {}
    for cand in [c for c in final.active if c.effect in rivals or c == STEP]:
        cols = []
        for j in final.layout.params(cand):
            h = float(np.sqrt(max(cov[np.searchsorted(final.idx, j)], 0.0)))
            if h <= 0:
                continue
            beta = final.beta.copy()
            beta[j] += h
            change = predict(final.obs, beta, final.layout, final.active, final.clip, final.structure) - base
            change = np.where(final.use, change, 0.0)
            cols.append(np.stack([np.bincount(idx, change[:, r], ids.size) for r in range(3)], axis=1) / safe)
        out[cand.key] = np.stack(cols, axis=1) if cols else np.zeros((ids.size, 0, 3))
    return out


def segment_test(final: ModelFit, reduced: ModelFit, cand: Candidate, noise: OffsetNoise,
                  slopes: dict[str, np.ndarray]) -> WanderTest | None:
    """The extension's pattern in the segment means against the offsets'
    noise (module docstring), the rates' offsets and the other selected
    offset effects (``slopes``, ``offset_slopes``) left free, by the
    likelihood ratio with the wander fitted under both hypotheses
    (``_likelihood_ratio``)."""
    seg = final.obs.segment
    ids, idx = np.unique(seg, return_inverse=True)
    if not all(int(s) in noise.u for s in ids):
        return None
    c, d, count, constant = _segment_means(final, reduced, ids, idx)
    if constant <= 0:
        return None
    var = np.array([noise.u[int(s)] for s in ids]) ** 2
    floor = np.array([noise.floor[int(s)] for s in ids])
    ok = (count > 0) & np.isfinite(var) & (var > 0)
    t = final.obs.motion.t_s
    start, stop = np.full(ids.size, np.inf), np.full(ids.size, -np.inf)
    np.minimum.at(start, idx, t)
    np.maximum.at(stop, idx, t)
    rate = np.zeros(ids.size, int)
    rate[idx] = final.obs.rate_idx
    indicators = (rate[:, None] == np.unique(rate)[None, :]).astype(float)
    fixed = np.concatenate([np.repeat(indicators[:, :, None], 3, axis=2)]
                           + [v for key, v in slopes.items() if key != cand.key], axis=1)
    within = np.maximum(var - floor**2, 1e-300)   # the fit's own variance, without the floor between segments
    # the fits size their floor about one common offset, so it holds the pattern of whatever moves segments'
    # offsets (an axis tilt made a floor of 90 counts, which then explained the tilt): every pattern is tested
    # with the wander refitted under both hypotheses. The noise model's walk is not taken as known: a
    # Gauss-Markov wander slower than the segments reads as a walk within them (K 0.2 for the mix's 300 s,
    # 2-count term) but saturates between them, and would explain true drifts
    stat, wander = _likelihood_ratio(c, d, within, ok, fixed, start, stop)
    return WanderTest(stat, constant, wander)


def wander_shapes(start: np.ndarray, stop: np.ndarray) -> tuple[list[np.ndarray], list[float], np.ndarray]:
    """The wander's correlation between segment means per unit variance,
    with its correlation times: independent offsets (0) and first-order
    Gauss-Markov terms exp(-|t_i - t_j| / T) at the segments' mid-times for
    T over ``WANDER_TIMES`` of the recording's duration; and a random walk's
    covariance per unit K^2 (IEEE Std 952: Var = K^2 t from the record's
    start), min(s, t) averaged over both segments' windows (``noise.means``)."""
    duration = float(stop.max() - start.min())
    centre = (start + stop) / 2
    lag = np.abs(centre[:, None] - centre[None, :])
    times = [share * duration for share in WANDER_TIMES] if duration > 0 else []
    shapes = [np.eye(start.size)] + [np.exp(-lag / tau) for tau in times]
    walk = window_mean_covariance(NoiseProcess(random_walk_k=1.0), start, stop, 1e-9, (float(start.min()), float(stop.max())))
    return shapes, [0.0, *times], walk


def _likelihood_ratio(c: np.ndarray, d: np.ndarray, within: np.ndarray, ok: np.ndarray, fixed: np.ndarray,
                      start: np.ndarray, stop: np.ndarray) -> tuple[float, tuple[WanderFit | None, ...]]:
    """(2 ln LR of the pattern ``d`` in the segment means ``c``, the wander
    fitted under the null per channel). Each hypothesis has its own wander,
    V = diag(``within``) + q^2 S, S one of ``wander_shapes`` (the walk's
    per unit variance at the record's end among them) and q on a
    grid to ten times the means' spread, fitted by maximum likelihood per
    channel. The means are residuals of a model whose rates' offsets and
    other offset effects (``fixed``: segments, columns, channels) were
    fitted too, so the likelihoods are those of the contrasts free of them
    (restricted maximum likelihood, Patterson & Thompson 1971, Biometrika
    58, 545); d's size is free per channel."""
    shapes, taus, walk = wander_shapes(start, stop)
    duration = float(stop.max() - start.min())
    if duration > 0:   # the walk per unit variance at the record's end
        shapes, taus = [*shapes, walk / duration], [*taus, np.inf]
    # per channel: (log det + m'V^-1 m, m'V^-1 x, x'V^-1 x) over the grid
    curves: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    wander: list[WanderFit | None] = []
    for r in range(3):
        on = ok[:, r]
        design = fixed[on][:, :, r]
        u, sv, _ = np.linalg.svd(design, full_matrices=True)
        rank = int(np.sum(sv > sv[0] * 1e-9)) if sv.size and sv[0] > 0 else 0
        basis = u[:, rank:]   # the contrasts free of the fixed patterns
        if basis.shape[1] < 2:
            wander.append(None)
            continue
        m, x = basis.T @ c[on, r], basis.T @ d[on, r]
        spread = float(np.sqrt(np.mean(m**2)))
        q = np.r_[0.0, spread * np.geomspace(0.03, 10.0, 16)]
        local = np.stack([basis.T @ s[np.ix_(on, on)] @ basis for s in shapes])   # (shapes, k, k)
        v = basis.T @ np.diag(within[on, r]) @ basis + q[:, None, None, None] ** 2 * local[None]
        chol = np.linalg.cholesky(v)
        wm = np.linalg.solve(chol, np.broadcast_to(m[:, None], v.shape[:-1] + (1,)))[..., 0]
        wx = np.linalg.solve(chol, np.broadcast_to(x[:, None], v.shape[:-1] + (1,)))[..., 0]
        logdet = 2 * np.sum(np.log(np.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
        a, b, cc = (logdet + np.sum(wm**2, -1)).ravel(), np.sum(wm * wx, -1).ravel(), np.sum(wx**2, -1).ravel()
        curves.append((a, b, cc))
        best = int(np.argmin(a))
        wander.append(WanderFit(float(q[best // len(shapes)]), taus[best % len(shapes)], duration))
    if not curves:
        return 0.0, tuple(wander)
    # -2 ln L(beta) per grid point is a + beta^2 cc - 2 beta b: the null at beta = 0, the alternative at the best
    # beta, which lies between the grid points' own optima b / cc (the profile is the envelope of parabolas)
    null = sum(float(a.min()) for a, _, _ in curves)
    alt = 0.0
    for a, b, cc in curves:
        opt = b[cc > 0] / cc[cc > 0]
        beta = np.r_[0.0, np.linspace(opt.min(), opt.max(), 801)] if opt.size else np.zeros(1)
        alt += float(np.min(a[:, None] + beta[None, :] ** 2 * cc[:, None] - 2 * beta[None, :] * b[:, None]))
    return max(0.0, null - alt), tuple(wander)
