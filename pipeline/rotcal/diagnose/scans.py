"""Scans of the final residuals for structure no catalogue effect explains.

Each scan is a test with a stated false-alarm rate (its family-wise p-value
is compared with ``alpha``) and reports where the structure lies and what it
looks like, in the output unit, so that a calibration engineer can check it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import fdtrc, gammaincc, gammaln

from rotcal.diagnose.fitting import chi2_sf
from rotcal.fit.spectrum import density_ratio_at, periodogram
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
    run: np.ndarray | None = None   # runs of samples in time succession (``Observations.run``); None: the segments


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
# the tone scan's local noise level: the mean ordinate over up to this many bins either side of the
# bin tested, leaving out the nearest (a tone's leakage, the zero padding's correlation)
TONE_LEVEL_BINS = 32
TONE_GAP_BINS = 3


def local_level(total: np.ndarray, count: np.ndarray, half_width: int = TONE_LEVEL_BINS,
                gap: int = TONE_GAP_BINS) -> tuple[np.ndarray, np.ndarray]:
    """(sum of ordinates, their count) over the bins ``gap`` to k_j either
    side of each bin j, k_j = ``half_width`` or less, so that the window
    stays symmetric about j within the bins holding any ordinate: a smooth
    spectrum's slope cancels in it, and only its curvature is left."""
    n = total.size
    have = np.flatnonzero(count > 0)
    if have.size == 0:
        return np.zeros(n), np.zeros(n)
    j = np.arange(n)
    k = np.minimum(np.minimum(j - have[0], have[-1] - j), half_width)
    on = k >= gap
    sums = []
    for x in (total, count):
        cs = np.r_[0.0, np.cumsum(x)]
        left = cs[np.clip(j - gap + 1, 0, n)] - cs[np.clip(j - k, 0, n)]
        right = cs[np.clip(j + k + 1, 0, n)] - cs[np.clip(j + gap, 0, n)]
        sums.append(np.where(on, left + right, 0.0))
    return sums[0], sums[1]


def tone_scan(res: Residuals, alpha: float, harmonics: int = 6) -> list[Unexplained]:
    """Tones unrelated to the rotation: the periodograms of the rotation
    segments' residuals, summed per channel on a common frequency grid, with
    rotation harmonics and the lowest frequencies left out, each bin against
    the noise's local level (``local_level``), not a white one: the noise
    may be coloured (a sensor's filter, a wander). With each ordinate
    ~ L Exp(1) about a smooth level L, a bin's sum over m segments over the
    window's mean of M ordinates is F(2m, 2M) (Percival & Walden 1993,
    section 10.9's test against the local spectrum), M counted at the zero
    padding's share of independent ordinates."""
    segs = [(sid, part) for sid, part in _segments(res) if res.rotating[part.start] and part.stop - part.start > TONE_MIN_SAMPLES]
    if not segs:
        return []
    dt = float(np.median(np.diff(res.t_s[segs[0][1]])))
    n_pad = 1 << int(np.ceil(np.log2(max(p.stop - p.start for _, p in segs))))
    independent_share = float(np.mean([(p.stop - p.start) / n_pad for _, p in segs]))
    freqs = np.fft.rfftfreq(n_pad, dt)
    out = []
    for r, channel in enumerate(CHANNELS):
        total = np.zeros(freqs.size)
        count = np.zeros(freqs.size)
        powers = []
        for sid, part in segs:
            use = res.use[part, r]
            n = int(use.sum())
            if n <= TONE_MIN_SAMPLES:  # a channel clipped through most of the segment leaves no spectrum
                continue
            # each segment at its own level: a noisier segment (a vibrating rate) would otherwise dominate
            # the sum, whose law would be that of fewer segments
            level_seg = float(np.sqrt(np.sum(np.where(use, res.resid[part, r], 0.0) ** 2) / n)) or float(res.sigma[r])
            e = np.where(use, res.resid[part, r] / level_seg, 0.0)
            power = np.abs(np.fft.rfft(e, n_pad)) ** 2 / max(n, 1)
            duration = n * dt
            rate = abs(res.rate_hz[part.start])
            valid = freqs > 5.0 / duration
            valid &= freqs < 0.95 / (2 * dt)
            for h in range(harmonics + 1):
                valid &= np.abs(freqs - h * rate) > 3.0 / duration
            total += np.where(valid, power, 0.0)
            count += valid
            powers.append((sid, part, power, n, level_seg))
        level_sum, level_count = local_level(total, count)
        ok = (count > 0) & (level_count > 0) & (level_sum > 0)
        if not ok.any():
            continue
        level = np.where(ok, level_sum / np.where(ok, level_count, 1.0), 1.0)
        ratio = np.where(ok, total / np.maximum(count, 1) / level, 0.0)
        p_bins = np.where(ok, fdtrc(2 * np.maximum(count, 1), 2 * np.maximum(level_count * independent_share, 1), ratio), 1.0)
        j = int(np.argmin(p_bins))
        independent = max(p.stop - p.start for _, p in segs) / 2
        p_family = min(1.0, p_bins[j] * independent * 3)
        if p_family >= alpha:
            continue
        f = freqs[j]
        excess = max(ratio[j] - 1.0, 0.0) * level[j]   # the tone's share of the bin over the local level
        share = excess / max(ratio[j] * level[j], 1e-300)   # of each segment's ordinate
        amps = np.array([2 * sd * np.sqrt(share * pw[j] / n) for _, _, pw, n, sd in powers])
        present = [sid for (sid, part, pw, n, _) in powers if gammaincc(1, pw[j] / level[j]) < 0.01]
        reduction = np.zeros(3)
        reduction[r] = sum(pw[j] * sd**2 for _, _, pw, _, sd in powers) * share
        where = f"channel {channel}, {len(present)} of {len(segs)} rotation segments"
        out.append(Unexplained(
            "tone", where,
            f"tone at {f:.3g} Hz, {np.median(amps):.2g} {res.output_unit} in channel {channel}, "
            f"in {len(present)} of {len(segs)} rotation segments, {ratio[j]:.3g} times the noise's local level "
            f"(not a harmonic of any rotation rate; {p_is(p_family)})",
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


def harmonic_density(e: np.ndarray, starts: np.ndarray, rates_hz: np.ndarray, dt_s: float, orders) -> np.ndarray:
    """Per segment (rows ``starts[k]:starts[k+1]`` of ``e``, standardised
    residuals) and order k, the noise's density at k times the segment's
    rotation frequency in units of e^2 (1 for white noise of e's level):
    the segment's mean square times the density's ratio to white there,
    read from the segments' periodograms pooled on one frequency axis
    (``fit.spectrum.density_ratio_at``: 1 where white noise explains it, so
    white noise keeps its test). Grenander 1954: a sine term's variance is
    white noise's at the density of its frequency."""
    bounds = np.r_[starts, e.size]
    grams = [periodogram(e[a:b, None], dt_s, abs(rate) * (b - a) * dt_s) for a, b, rate in zip(bounds[:-1], bounds[1:], rates_hz)]
    pooled: dict[int, tuple[np.ndarray, float]] = {}
    for gram in grams:
        for k, sums, count in zip(gram.bands, gram.sums, gram.counts):
            old = pooled.get(int(k), (np.zeros(1), 0.0))
            pooled[int(k)] = (old[0] + sums, old[1] + float(count))
    out = np.ones((starts.size, len(orders)))
    for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:])):
        level = float(e[a:b] @ e[a:b]) / (b - a)
        for j, k in enumerate(orders):
            out[i, j] = level * float(density_ratio_at(pooled, k * abs(rates_hz[i]), grams[i].resolution_hz)[0])
    return out


def harmonic_scan(res: Residuals, alpha: float, orders=(2, 3, 4, 5, 6)) -> list[Unexplained]:
    """Harmonics k theta of the rotation in the residuals of each axis's
    rotation segments, per channel (chi-square with 2 per segment), each
    segment's against the noise's density at its harmonic's frequency
    (``harmonic_density``)."""
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
        dt = float(np.median(np.diff(res.t_s[segs[0][1]])))
        density = harmonic_density(e, starts, np.array([res.rate_hz[part.start] for _, part in segs]), dt, orders)
        for j, (k, wave) in enumerate(zip(orders, waves)):
            if at is None and k not in grams:
                grams[k] = _segment_grams(wave, starts)
            x2, coef = _segment_chi2(e, wave, starts, grams[k]) if at is None else _segment_chi2(e, wave[at], starts)
            x2 = x2 / density[:, j]
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
