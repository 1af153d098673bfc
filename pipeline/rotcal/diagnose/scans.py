"""Scans of the final residuals for structure no catalogue effect explains.

Each scan is a test with a stated false-alarm rate (its family-wise p-value
is compared with ``alpha``) and reports where the structure lies and what it
looks like, in the output unit, so that a calibration engineer can check it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import gammaincc, gammaln, ndtr

from rotcal.diagnose.fitting import chi2_sf
from rotcal.model.physics import AXES, CHANNELS


def normal_p(values: np.ndarray) -> float:
    """The p-value of the D'Agostino-Pearson K^2 test of normality (D'Agostino,
    Belanger & D'Agostino 1990): the skewness test (D'Agostino 1970) and the
    kurtosis test (Anscombe & Glynn 1983, Eqs. 1-5) squared and summed,
    against chi-square on 2 degrees of freedom. ``scipy.stats.normaltest``'s
    formulas in its operation order, so the same value to the bit (tested):
    written out because ``scipy.stats`` costs 0.32 s of CPU to import, in
    every batch worker and every ``rotcal run``, for this one test (its other
    uses here are scipy.special functions). Needs at least 8 values."""
    n = np.asarray(float(values.size))
    d = values - np.mean(values)
    m2, d2 = np.mean(d**2), d**2
    b1, b2 = np.mean(d2 * d) / m2**1.5, np.mean(d2**2) / m2**2.0
    with np.errstate(divide="ignore", invalid="ignore"):
        y = b1 * np.sqrt(((n + 1) * (n + 3)) / (6.0 * (n - 2)))
        beta2 = 3.0 * (n**2 + 27 * n - 70) * (n + 1) * (n + 3) / ((n - 2.0) * (n + 5) * (n + 7) * (n + 9))
        w2 = -1 + np.sqrt(2 * (beta2 - 1))
        delta, alpha = 1 / np.sqrt(0.5 * np.log(w2)), np.sqrt(2.0 / (w2 - 1))
        y = np.where(y == 0, 1.0, y)
        z_skew = delta * np.log(y / alpha + np.sqrt((y / alpha) ** 2 + 1))
        mean_b2 = 3.0 * (n - 1) / (n + 1)
        var_b2 = 24.0 * n * (n - 2) * (n - 3) / ((n + 1) * (n + 1.0) * (n + 3) * (n + 5))
        x = (b2 - mean_b2) / var_b2**0.5
        sqrt_beta1 = 6.0 * (n * n - 5 * n + 2) / ((n + 7) * (n + 9)) * ((6.0 * (n + 3) * (n + 5)) / (n * (n - 2) * (n - 3))) ** 0.5
        a = 6.0 + 8.0 / sqrt_beta1 * (2.0 / sqrt_beta1 + (1 + 4.0 / (sqrt_beta1**2)) ** 0.5)
        denom = 1 + x * (2 / (a - 4.0)) ** 0.5
        term2 = np.sign(denom) * np.where(denom == 0.0, np.nan, ((1 - 2.0 / a) / np.abs(denom)) ** (1 / 3))
        z_kurt = ((1 - 2 / (9.0 * a)) - term2) / (2 / (9.0 * a)) ** 0.5
    return chi2_sf(z_skew * z_skew + z_kurt * z_kurt, 2.0)


@dataclass(frozen=True)
class Unexplained:
    """An unexplained finding: where, what, how sure, and what modelling it
    would remove (residual sum of squares per channel, parameters used)."""

    kind: str
    where: str
    evidence: str
    p_value: float
    rss_reduction: np.ndarray
    n_params: int


@dataclass(frozen=True, eq=False)
class Residuals:
    """Final residuals with what the scans need to locate them."""

    t_s: np.ndarray
    resid: np.ndarray        # (n, 3), output units, 0 where unused
    use: np.ndarray          # (n, 3)
    sigma: np.ndarray        # (3,)
    segment: np.ndarray
    axis_idx: np.ndarray
    rate_hz: np.ndarray
    rotating: np.ndarray
    theta_deg: np.ndarray    # commanded angle
    output_unit: str


def counted(n: int, noun: str) -> str:
    """"1 parameter", "3 parameters": a count with its noun in the right number."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def p_is(p: float) -> str:
    """A p-value as evidence reads it: "p = 3.1e-05", or "p < 1e-300" below
    the smallest double a tail probability is computed to."""
    return f"p = {p:.1e}" if p >= 1e-300 else "p < 1e-300"


def _segments(res: Residuals):
    """(segment id, sample slice) in time order; segments are contiguous."""
    edges = np.flatnonzero(np.r_[True, np.diff(res.segment) != 0, True])
    return [(int(res.segment[a]), slice(a, b)) for a, b in zip(edges[:-1], edges[1:])]


def _describe(res: Residuals, part: slice) -> str:
    rate = res.rate_hz[part.start]
    return f"axis {AXES[res.axis_idx[part.start]]} {'static' if rate == 0 else f'{rate:g} Hz'}"


def step_scan_p(statistic: float, n: int, dof: int = 3) -> float:
    """False-alarm probability of the largest chi-square(dof) statistic of a
    single change in mean over n positions (Siegmund 1988 approximation for
    the supremum of a standardised CUSUM process)."""
    x = statistic
    if x <= dof:
        return 1.0
    log_density = (dof / 2) * np.log(x) - x / 2 - (dof / 2) * np.log(2) - gammaln(dof / 2)
    factor = (1 - dof / x) * 2 * np.log(max(n - 1, 2)) + 4 / x
    return float(min(1.0, np.exp(log_density) * factor))


def step_scan(res: Residuals) -> tuple[float, float, float]:
    """The most likely time of a step in the mean of all channels together:
    (time in s, statistic, p-value). Positions within 10 samples of the ends
    are not scanned; where fewer samples than that have all three channels
    usable (clipping sets different channels aside at different times),
    there is no position to test and the p-value is 1."""
    order = np.argsort(res.t_s, kind="stable")
    # in time order, the samples with all three channels usable; the channels'
    # masks and squares combined column by column (the same values as
    # ``all``/``sum`` over the rows' three entries, in a third of the time)
    usable = res.use[:, 0] & res.use[:, 1] & res.use[:, 2]
    order = order[usable[order]]
    e = np.take(res.resid, order, axis=0)
    e /= res.sigma[None, :]
    n = e.shape[0]
    if n < 22:
        return float(np.median(res.t_s)), 0.0, 1.0
    k = np.arange(1, n)
    s = np.cumsum(e, axis=0)[:-1]
    squares = np.square(s - (k / n)[:, None] * s[-1])  # of the centred cumulative sums
    stat = (squares[:, 0] + squares[:, 1]) + squares[:, 2]
    stat /= k * (n - k) / n
    inner = slice(10, n - 11)
    j = int(np.argmax(stat[inner])) + inner.start
    t = res.t_s[order]
    return float(0.5 * (t[j] + t[j + 1])), float(stat[j]), step_scan_p(float(stat[j]), n)


# fewest usable samples of one segment and channel whose periodogram the tone scan sums
TONE_MIN_SAMPLES = 64


def tone_scan(res: Residuals, alpha: float, harmonics: int = 6) -> list[Unexplained]:
    """Tones unrelated to the rotation: the periodograms of the rotation
    segments' residuals, summed per channel on a common frequency grid
    (each ordinate ~ Exp(1) for white noise, a sum over m segments ~ Gamma(m)),
    with rotation harmonics and the lowest frequencies left out."""
    segs = [(sid, part) for sid, part in _segments(res) if res.rotating[part.start] and part.stop - part.start > TONE_MIN_SAMPLES]
    if not segs:
        return []
    dt = float(np.median(np.diff(res.t_s[segs[0][1]])))
    n_pad = 1 << int(np.ceil(np.log2(max(p.stop - p.start for _, p in segs))))
    freqs = np.fft.rfftfreq(n_pad, dt)
    out = []
    for r, channel in enumerate(CHANNELS):
        total = np.zeros(freqs.size)
        count = np.zeros(freqs.size)
        powers = []
        for sid, part in segs:
            use = res.use[part, r]
            e = np.where(use, res.resid[part, r] / res.sigma[r], 0.0)
            n = int(use.sum())
            if n <= TONE_MIN_SAMPLES:  # a channel clipped through most of the segment leaves no spectrum
                continue
            power = np.abs(np.fft.rfft(e, n_pad)) ** 2 / max(n, 1)
            duration = n * dt
            rate = abs(res.rate_hz[part.start])
            valid = freqs > 5.0 / duration
            valid &= freqs < 0.95 / (2 * dt)
            for h in range(harmonics + 1):
                valid &= np.abs(freqs - h * rate) > 3.0 / duration
            total += np.where(valid, power, 0.0)
            count += valid
            powers.append((sid, part, power, n))
        ok = count > 0
        if not ok.any():
            continue
        p_bins = np.where(ok, gammaincc(np.maximum(count, 1), total), 1.0)
        j = int(np.argmin(p_bins))
        independent = max(p.stop - p.start for _, p in segs) / 2
        p_family = min(1.0, p_bins[j] * independent * 3)
        if p_family >= alpha:
            continue
        f = freqs[j]
        amps = np.array([2 * res.sigma[r] * np.sqrt(pw[j] / n) for _, _, pw, n in powers])
        present = [sid for (sid, part, pw, n) in powers if gammaincc(1, pw[j]) < 0.01]
        reduction = np.zeros(3)
        reduction[r] = sum(pw[j] for _, _, pw, _ in powers) * res.sigma[r] ** 2
        where = f"channel {channel}, {len(present)} of {len(segs)} rotation segments"
        out.append(Unexplained(
            "tone", where,
            f"tone at {f:.3g} Hz, {np.median(amps):.2g} {res.output_unit} in channel {channel}, "
            f"in {len(present)} of {len(segs)} rotation segments (not a harmonic of any rotation rate; {p_is(p_family)})",
            p_family, reduction, 2 * len(segs),
        ))
    return out


def _segment_grams(basis: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Per segment (rows ``starts[k]:starts[k+1]``), the Gram matrix of ``basis`` (n, q)."""
    q = basis.shape[1]
    # the products of each pair of basis columns once (the Gram matrices are symmetric)
    i, j = np.triu_indices(q)
    # each pair's product into its column (gathering the pairs' columns first copied the basis twice: 2x slower)
    products = np.empty((basis.shape[0], i.size))
    for k, (a, b) in enumerate(zip(i, j)):
        np.multiply(basis[:, a], basis[:, b], out=products[:, k])
    sums = np.add.reduceat(products, starts, axis=0)
    gram = np.empty((starts.size, q, q))
    gram[:, i, j] = sums
    gram[:, j, i] = sums
    return gram


def _segment_chi2(e: np.ndarray, basis: np.ndarray, starts: np.ndarray,
                  gram: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per segment (rows ``starts[k]:starts[k+1]``), the chi-square of the
    standardised residuals ``e`` explained by regressing them on ``basis``
    (n, q), and the coefficients: normal equations summed per segment
    (``gram``: the basis's ``_segment_grams``, when another channel on the
    same rows has them already)."""
    q = basis.shape[1]
    gram = _segment_grams(basis, starts) if gram is None else gram
    rhs = np.add.reduceat(basis * e[:, None], starts, axis=0)
    coef = np.linalg.solve(gram + np.eye(q)[None] * 1e-12, rhs[..., None])[..., 0]
    return np.einsum("ki,ki->k", coef, rhs), coef


def _used_segments(res: Residuals, r: int, keep) -> tuple[np.ndarray, np.ndarray, list]:
    """Rows used for channel r in the segments ``keep`` accepts, with the
    start of each segment's block in them and the segment slices."""
    segs = [(sid, part) for sid, part in _segments(res) if keep(part)]
    rows = [np.arange(part.start, part.stop)[res.use[part, r]] for _, part in segs]
    segs = [sp for sp, rw in zip(segs, rows) if rw.size >= 10]
    rows = [rw for rw in rows if rw.size >= 10]
    if not rows:
        return np.zeros(0, int), np.zeros(0, int), []
    starts = np.cumsum([0] + [rw.size for rw in rows[:-1]])
    return np.concatenate(rows), starts, segs


def _harmonics(theta: np.ndarray, orders) -> list[np.ndarray]:
    """(cos, sin) of k theta for each order k, as the columns of an (n, 2)
    array each: the powers of one complex exponential, each a view of the
    complex array (a sine and a cosine per order took 3.8 ms a default-plan
    dataset; the rounding grows as k, to 1e-15 at k = 6)."""
    unit = np.exp(1j * theta)
    power, waves = unit, {}
    for k in range(1, max(orders) + 1):
        power = power if k == 1 else power * unit
        waves[k] = power.view(np.float64).reshape(-1, 2)
    return [waves[k] for k in orders]


def harmonic_scan(res: Residuals, alpha: float, orders=(2, 3, 4, 5, 6)) -> list[Unexplained]:
    """Harmonics k theta of the rotation in the residuals of each axis's
    rotation segments, per channel (chi-square with 2 per segment)."""
    tests = []
    # the harmonics of every rotating sample once; each channel takes its used rows
    rotating = np.flatnonzero(res.rotating)
    theta = np.deg2rad(res.theta_deg[rotating])
    waves = _harmonics(theta, orders)
    grams: dict[int, np.ndarray] = {}  # of the channels that use every rotating sample (the same rows)
    for r, channel in enumerate(CHANNELS):
        rows, starts, segs = _used_segments(res, r, lambda part: res.rotating[part.start])
        if not segs:
            continue
        e = res.resid[rows, r] / res.sigma[r]
        at = None if rows.size == rotating.size else np.searchsorted(rotating, rows)
        seg_axis = np.array([res.axis_idx[part.start] for _, part in segs])
        for k, wave in zip(orders, waves):
            if at is None and k not in grams:
                grams[k] = _segment_grams(wave, starts)
            x2, coef = _segment_chi2(e, wave, starts, grams[k]) if at is None else _segment_chi2(e, wave[at], starts)
            for ax in np.unique(seg_axis):
                on = seg_axis == ax
                stat = float(x2[on].sum())
                amps = np.hypot(coef[on, 0], coef[on, 1]) * res.sigma[r]
                tests.append((chi2_sf(stat, 2 * on.sum()), r, channel, int(ax), k, stat, amps, int(on.sum())))
    out = []
    for p, r, channel, ax, k, stat, amps, m in tests:
        p_family = min(1.0, p * len(tests))
        if p_family < alpha:
            reduction = np.zeros(3)
            reduction[r] = stat * res.sigma[r] ** 2
            out.append(Unexplained(
                "harmonic", f"channel {channel}, axis {AXES[ax]} rotation segments",
                f"harmonic {k} of the rotation, {np.median(amps):.2g} {res.output_unit} in channel {channel} "
                f"during rotation about {AXES[ax]} (chi-square {stat:.0f} on {2 * m}; {p_is(p_family)})",
                p_family, reduction, 2 * m,
            ))
    return out


def segment_scan(res: Residuals, alpha: float) -> list[Unexplained]:
    """Per segment and channel, what is left in a constant, the first
    harmonic and a linear trend: the segments disagreeing with the combined
    model (Geist 2017 section 3 consistency) or drifting within themselves."""
    out = []
    n_rates = len(np.unique(res.rate_hz))
    theta = np.deg2rad(res.theta_deg)
    first_harmonic = np.empty((theta.size, 3))  # every sample's, once, written in place
    first_harmonic[:, 0] = 1.0
    np.sin(theta, out=first_harmonic[:, 1])
    np.cos(theta, out=first_harmonic[:, 2])
    used = [_used_segments(res, r, lambda part: True) for r in range(3)]
    for kind in ("inconsistent", "trend"):
        stats = []  # (chi2, dof, segment id, slice, channel, coefficient of interest)
        shared = None  # the Gram matrices of the channels that use every sample (the same rows)
        for r in range(3):
            rows, starts, segs = used[r]
            if not segs:
                continue
            e = res.resid[rows, r] / res.sigma[r]
            whole = rows.size == theta.size
            if kind == "inconsistent":
                basis = first_harmonic if whole else first_harmonic[rows]
            else:
                t = res.t_s[rows]
                mean_t = np.add.reduceat(t, starts) / np.diff(np.r_[starts, t.size])
                basis = (t - np.repeat(mean_t, np.diff(np.r_[starts, t.size])))[:, None]
            if whole and shared is None:
                shared = _segment_grams(basis, starts)
            x2, coef = _segment_chi2(e, basis, starts, shared if whole else None)
            for k, (sid, part) in enumerate(segs):
                stats.append((float(x2[k]), basis.shape[1], sid, part, r, coef[k]))
        if not stats:
            continue
        total = sum(st[0] for st in stats)
        dof = sum(st[1] for st in stats) - (12 * n_rates if kind == "inconsistent" else 0)
        p = min(1.0, chi2_sf(total, max(dof, 1)) * 2)
        if p >= alpha:
            continue
        _, _, sid, part, r, coef = max(stats, key=lambda st: st[0])
        reduction = np.zeros(3)
        for st in stats:
            reduction[st[4]] += st[0] * res.sigma[st[4]] ** 2
        size = np.abs(coef).max() * res.sigma[r]
        what = ("a constant or first-harmonic misfit" if kind == "inconsistent"
                else f"a trend of {coef[0] * res.sigma[r]:.2g} {res.output_unit} per s")
        out.append(Unexplained(
            kind, f"segment {sid} ({_describe(res, part)}), channel {CHANNELS[r]} most",
            f"segments depart from the combined model by {what} (largest: {size:.2g} {res.output_unit} in segment {sid}, "
            f"channel {CHANNELS[r]}; chi-square {total:.0f} on {dof}; {p_is(p)})",
            p, reduction, dof,
        ))
    return out


def static_step_scan(res: Residuals, step_id: np.ndarray, alpha: float) -> list[Unexplained]:
    """Geist 2017 Appendix B on the static steps' samples before averaging:
    no correlation and normality. Each step's samples are taken about their
    own mean and pooled over steps (a common noise is the model's premise),
    so the tests are those of one large sample: the lag-1 autocorrelation
    (E = -1/n for a demeaned step of n samples, variance 1/N) and the
    D'Agostino-Pearson K^2 test. Combining per-step p-values instead (Fisher)
    is anti-conservative: K^2 is not calibrated at 50 samples."""
    out = []
    static = ~res.rotating & (step_id >= 0)
    _, first, size = np.unique(step_id[static], return_index=True, return_counts=True)
    rows = np.flatnonzero(static)
    for r, channel in enumerate(CHANNELS):
        pooled, lag_sum, ss_sum, bias = [], 0.0, 0.0, 0.0
        for n in np.unique(size[size >= 20]):
            idx = rows[first[size == n]][:, None] + np.arange(n)[None, :]
            ok = res.use[idx, r].all(axis=1)
            x = res.resid[idx[ok], r]
            x = x - x.mean(axis=1, keepdims=True)
            pooled.append(x.ravel())
            lag_sum += float(np.sum(x[:, 1:] * x[:, :-1]))
            ss_sum += float(np.sum(x * x))
            bias += x.shape[0] * n * (-1.0 / n)
        if not pooled:
            continue
        values = np.concatenate(pooled)
        if values.size < 200 or ss_sum == 0:
            continue
        r1 = lag_sum / ss_sum
        z = (r1 - bias / values.size) * np.sqrt(values.size)
        for kind, p, what in (
            ("correlated", 2 * float(ndtr(-abs(z))), f"lag-1 autocorrelation {r1 + 0.0:.3f} (z = {z:.1f})"),
            ("non_normal", normal_p(values), "non-normal scatter"),
        ):
            p_family = min(1.0, p * 6)
            if p_family < alpha:
                out.append(Unexplained(
                    kind, f"static steps, channel {channel}",
                    f"static-step samples of channel {channel} show {what} (Geist 2017 Appendix B; {values.size} "
                    f"samples of {int(np.sum(size >= 20))} steps, {p_is(p_family)})", p_family, np.zeros(3), 0,
                ))
    return out
