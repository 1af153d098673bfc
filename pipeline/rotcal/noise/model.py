"""A channel's noise model fitted to its Allan variance: the terms of
IEEE Std 952-1997 Annex C and IEEE Std 1293-2018 Annex A,

    sigma^2(tau) = 3 Q^2 / tau^2 + N^2 / tau + (2 ln 2 / pi) B^2 + K^2 tau / 3
                   + sum_j GM(tau; q_j, T_j),

GM the Allan variance of a first-order Gauss-Markov term of stationary sd q
and correlation time T (from its autocovariance q^2 exp(-|t| / T)):
(q T / tau)^2 (2 u - 3 + 4 exp(-u) - exp(-2 u)), u = tau / T.

Fitted by weighted least squares on the octave Allan variances, each
weighted by its own variance 2 sigma^4 / edf (the Allan variance estimate
is chi-square with edf degrees of freedom, NIST SP 1065 5.3), the edf for
the power-law type the model has at that tau, iterated with the model's
variances (so a low estimate does not weigh more than a high one). The
coefficients enter as variances (Q^2, N^2, B^2, K^2, q_j^2; non-negative),
the correlation times as log T. The number of Gauss-Markov terms (0 to 2)
is chosen by Akaike's criterion. Uncertainties: the covariance (J^T W J)^-1
scaled by the reduced chi-square where above 1 (a misfit widens, never
narrows) and by OCTAVE_CORRELATION^2 for the correlation of neighbouring
octave estimates (measured on seeded draws, docs/noise.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize, nnls

from rotcal.noise.allan import AllanVariance, pooled_avar, with_edf

FLICKER = 2 * math.log(2) / math.pi  # Allan variance of flicker over B^2 (IEEE Std 952 C.6)
POWER_TERMS = ("quantization", "white_density", "bias_instability", "random_walk")
MAX_GAUSS_MARKOV = 2
# the octave estimates share their samples, so weighted least squares that takes them as independent
# counts the same information several times: the uncertainties are widened by this factor, measured on
# seeded draws (docs/noise.md: without it 10 % of white-noise densities fell beyond 3 u)
OCTAVE_CORRELATION = 2.0


@dataclass(frozen=True)
class Term:
    """One identified term: its name (with the Gauss-Markov term's number),
    value, standard uncertainty and effective degrees of freedom, in the
    channel's unit (``unit`` says how: e.g. output unit sqrt(s))."""

    term: str
    index: int
    value: float
    u: float
    dof: float
    unit: str


@dataclass(frozen=True, eq=False)
class ChannelNoise:
    """A channel's Allan variance, its fitted model's terms and the fit's
    reduced chi-square; ``reason`` where no model could be fitted."""

    channel: str
    allan: AllanVariance
    terms: tuple[Term, ...]
    chi2_reduced: float
    dt: float = 1.0
    band_limit: float = 0.0  # the fitted coefficient of 3 / tau^2: Q^2, or negative where the output is band-limited
    reason: str | None = None

    def model_avar(self, tau_s: np.ndarray) -> np.ndarray:
        """The fitted model's Allan variance at ``tau_s`` (the quantization
        term with its fitted sign: a band-limited output's is negative)."""
        v = {(t.term, t.index): t.value for t in self.terms}
        p = np.array([v.get((name, 0), 0.0) ** 2 for name in POWER_TERMS])
        p[0] = self.band_limit
        gm = [(v[("gauss_markov_sd", j)], v[("gauss_markov_tau_s", j)]) for j in range(MAX_GAUSS_MARKOV)
              if ("gauss_markov_sd", j) in v]
        return _model(np.asarray(tau_s, float), p, gm, self.dt)


def gauss_markov_avar(tau: np.ndarray, q: float, t: float, dt: float) -> np.ndarray:
    """The Allan variance of a Gauss-Markov term sampled every ``dt``
    (autocovariance q^2 a^|k|, a = exp(-dt / T)): with S the sum of m
    samples, (Var S - Cov(S_1, S_2)) / m^2,

        Var S = q^2 (m + 2 a (m (1 - a) - (1 - a^m)) / (1 - a)^2),
        Cov   = q^2 a (1 - a^m)^2 / (1 - a)^2;

    for T above 1000 dt, where that cancels, the continuous form of the
    module docstring (the two differ there by less than 1e-3)."""
    m = np.maximum(np.round(tau / dt), 1.0)
    if t > 1000 * dt:
        u = tau / t
        small = u < 1e-3
        bracket = np.where(small, 2 * u**3 / 3 - u**4 / 2, 2 * u - 3 + 4 * np.exp(-u) - np.exp(-2 * u))
        return (q * t / tau) ** 2 * bracket
    a = math.exp(-dt / t)
    am = a**m
    var_s = m + 2 * a * (m * (1 - a) - (1 - am)) / (1 - a) ** 2
    cov_s = a * (1 - am) ** 2 / (1 - a) ** 2
    return q**2 * (var_s - cov_s) / m**2


def _basis(tau: np.ndarray) -> np.ndarray:
    """The power-law terms' Allan variance per unit variance coefficient (n, 4)."""
    return np.column_stack([3 / tau**2, 1 / tau, np.full(tau.size, FLICKER), tau / 3])


def _model(tau: np.ndarray, power: np.ndarray, gm: list[tuple[float, float]], dt: float) -> np.ndarray:
    out = _basis(tau) @ power
    for q, t in gm:
        out = out + gauss_markov_avar(tau, q, t, dt)
    return out


def _alphas(tau: np.ndarray, avar: np.ndarray) -> np.ndarray:
    """The power-law noise type at each tau from the local slope of the
    Allan variance (-1 white, 0 flicker, +1 random walk; alpha = -1 - slope)."""
    if tau.size < 2:
        return np.zeros(tau.size, int)
    slope = np.gradient(np.log(np.maximum(avar, 1e-300)), np.log(tau))
    return np.clip(np.round(-1 - slope), -2, 0).astype(int)


def _linear(tau: np.ndarray, a: np.ndarray, sd: np.ndarray, taus_c: tuple[float, ...],
            dt: float, power: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[np.ndarray, float, np.ndarray]:
    """The coefficients linear in the Allan variance (c_Q, N^2, B^2, K^2,
    q_j^2) for fixed correlation times, by bounded weighted least squares
    (``nnls``, columns scaled to unit norm), the power-law terms outside
    ``power`` held at 0: (coefficients, chi-square, the weighted design)."""
    basis = _basis(tau) * np.isin(np.arange(len(POWER_TERMS)), power)
    design = np.column_stack([basis, *(gauss_markov_avar(tau, 1.0, t, dt) for t in taus_c)]) / sd[:, None]
    norm = np.linalg.norm(design, axis=0)
    norm[norm == 0] = 1.0
    # the 3 / tau^2 coefficient may be negative: a low-pass takes from the shortest averaging times what
    # quantization adds (band-limited white noise: N^2 / tau minus a tau^-2 term beyond the filter's memory);
    # as the difference of two non-negative coefficients, the whole is a non-negative least-squares problem
    scaled = design / norm
    solution, _ = nnls(np.column_stack([scaled, -scaled[:, 0]]), a / sd, maxiter=50 * design.shape[1])
    coef = np.r_[solution[0] - solution[-1], solution[1:-1]] / norm
    r = design @ coef - a / sd
    return coef, float(r @ r), design


def _fit(av: AllanVariance, sd: np.ndarray, n_gm: int, dt: float, first: float | None = None,
         start: np.ndarray | None = None, power: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[np.ndarray, float, np.ndarray]:
    """The weighted least-squares fit with ``n_gm`` Gauss-Markov terms by
    variable projection: the linear coefficients solved for each set of
    correlation times, the times searched on a grid (one per octave; a
    second term's beside ``first``, the one-term fit's log T), or started
    at ``start``, and refined by Nelder-Mead on log T. (parameters c_Q, N^2, B^2, K^2, q_j^2, log T_j; chi-square;
    Jacobian of the weighted residuals, the log T columns by central differences)."""
    tau, a = av.tau_s, av.avar
    low, high = math.log(max(tau[0] / 4, 1.5 * dt)), math.log(tau[-1] * 4)  # shorter times are white noise

    def chi2(log_t: np.ndarray) -> float:
        if np.any(log_t < low) or np.any(log_t > high):
            return np.inf
        return _linear(tau, a, sd, tuple(np.exp(np.sort(log_t))), dt, power)[1]

    log_t = np.empty(0)
    if n_gm and start is not None:
        log_t = start
    elif n_gm:
        grid = np.arange(low, high + 1e-9, math.log(2))
        candidates = ([np.array([g]) for g in grid] if n_gm == 1 or first is None
                      else [np.array([first, g]) for g in grid if abs(g - first) > 0.3]) or [np.array([low, high])[:n_gm]]
        log_t = min(candidates, key=chi2)
    if n_gm:
        log_t = np.sort(minimize(chi2, log_t, method="Nelder-Mead", options={"xatol": 1e-2, "fatol": 1e-3}).x)
    coef, value, design = _linear(tau, a, sd, tuple(np.exp(log_t)), dt, power)
    columns = [design]
    for j in range(n_gm):  # d residual / d log T_j = q_j^2 d GM(tau; 1, T_j) / d log T_j
        step = 1e-5
        up, down = (gauss_markov_avar(tau, 1.0, math.exp(log_t[j] + h), dt) for h in (step, -step))
        columns.append((coef[4 + j] * (up - down) / (2 * step) / sd)[:, None])
    return np.r_[coef, log_t], value, np.hstack(columns)


def _reweighted(av: AllanVariance, dt: float, n_gm: int, first: float | None = None,
                power: tuple[int, ...] = (0, 1, 2, 3)) -> tuple[np.ndarray, float, np.ndarray]:
    """``_fit`` weighted by its own model's Allan variance, iterated once
    from the estimates' (x, chi2, jac)."""
    sd = av.avar * np.sqrt(2 / av.edf)
    start = None
    for _ in range(2):
        x, chi2, jac = _fit(av, sd, n_gm, dt, first, start, power)
        start = x[4 + n_gm:]  # the reweighted fit starts where the first ended
        gm = [(math.sqrt(x[4 + j]), math.exp(x[4 + n_gm + j])) for j in range(n_gm)]
        # the weights never above a thousandth of the observed variance's: a model that misses some
        # averaging time by orders (a deterministic misfit left in the residuals) would otherwise
        # weigh it by 1e300 and overflow the design
        sd = np.maximum(_model(av.tau_s, x[:4], gm, dt), 1e-3 * av.avar) * np.sqrt(2 / av.edf)
    return x, chi2, jac


def _select(av: AllanVariance, dt: float):
    """The model with the fewest Akaike-penalised chi-square over 0, 1, 2
    Gauss-Markov terms (a second tried only when a first helped), each fit's
    weights from its own model's Allan variance (iterated once from the
    estimates'); a model whose Gauss-Markov terms the data do not show (a
    variance q^2 below its u) is not taken, whatever its chi-square: a
    term of a correlation time near the sample interval otherwise shares
    the white noise with N. (aic, n_gm, x, chi2, jac)."""
    best = None
    for n_gm in range(MAX_GAUSS_MARKOV + 1):
        if av.tau_s.size <= free_parameters(n_gm) or (best is not None and best[1] < n_gm - 1):
            break
        first = float(best[2][5]) if best is not None and best[1] == 1 else None
        x, chi2, jac = _reweighted(av, dt, n_gm, first)
        if not (np.isfinite(chi2) and np.isfinite(jac).all()):
            break
        aic = chi2 + 2 * free_parameters(n_gm)
        if n_gm and not _shown(x, jac, chi2, av.tau_s.size, n_gm):
            continue
        if best is None or aic < best[0] - 1e-9:
            best = (aic, n_gm, x, chi2, jac)
    return best


def free_parameters(n_gm: int) -> int:
    """The model's parameters with ``n_gm`` Gauss-Markov terms (the power-law coefficients, q_j^2 and log T_j)."""
    return len(POWER_TERMS) + 2 * n_gm


def _reduced(chi2: float, n_tau: int, free: int) -> float:
    """The chi-square over its degrees of freedom (at least 1): ``n_tau`` averaging times less ``free`` parameters."""
    return chi2 / max(n_tau - free, 1)


def _covariance(jac: np.ndarray, chi2: float, n_tau: int, free: int) -> np.ndarray:
    """The parameters' covariance (module docstring) of a fit of ``free`` parameters."""
    chi2_red = _reduced(chi2, n_tau, free)
    return np.linalg.pinv(jac.T @ jac) * max(chi2_red, 1.0) * OCTAVE_CORRELATION**2


def _shown(x: np.ndarray, jac: np.ndarray, chi2: float, n_tau: int, n_gm: int) -> bool:
    """Whether every Gauss-Markov variance exceeds its standard uncertainty."""
    cov = _covariance(jac, chi2, n_tau, free_parameters(n_gm))
    return all(x[4 + j] > math.sqrt(max(cov[4 + j, 4 + j], 0.0)) for j in range(n_gm))


def fit_channel(channel: str, av: AllanVariance, dt: float, unit: str) -> ChannelNoise:
    """The channel's model (module docstring), or its reason when the Allan
    variance has too few averaging times (fewer than 5). A sensor's
    low-pass lowers the shortest averaging times below any of the terms:
    where the fit from the shortest tau misfits (reduced chi-square above
    3), the shortest one or two octaves are left out when that fits better."""
    if av.tau_s.size < 5 or not np.all(av.avar > 0):
        return ChannelNoise(channel, av, (), 0.0, dt, 0.0, "fewer than 5 averaging times with an Allan variance: "
                                                   "the residual pieces are too short for a noise model")
    best, kept = None, av
    for skip in range(3):
        part = AllanVariance(av.tau_s[skip:], av.avar[skip:], av.n_terms[skip:], av.edf[skip:])
        if part.tau_s.size < 5:
            break
        found = _select(part, dt)
        if found is None:
            break
        red = _reduced(found[3], part.tau_s.size, free_parameters(found[1]))
        if best is None or red < best[0]:
            best, kept = (red, found), part
        if red <= 3.0:
            break
    if best is None:
        return ChannelNoise(channel, av, (), 0.0, dt, 0.0, "no noise model fits the residuals' Allan variance "
                                                   "(a deterministic misfit dominates it)")
    _, (_, n_gm, x, chi2, jac) = best
    chi2_red = _reduced(chi2, kept.tau_s.size, free_parameters(n_gm))
    cov = _covariance(jac, chi2, kept.tau_s.size, free_parameters(n_gm))
    return ChannelNoise(channel, av, _terms(x, cov, n_gm, unit), chi2_red, dt, float(x[0]))


def bounded_channel(channel: ChannelNoise) -> ChannelNoise:
    """The channel's Allan variance fitted with white noise (and its
    band limit) and one Gauss-Markov term alone: a slow noise the
    averaging times show but are too few to split (the full model leaves
    no degree of freedom for a Gauss-Markov term below seven of them),
    taken as the bounded process it may be rather than as flicker
    extrapolated to the record's length (an autoregression at 0.9 read
    from 3 s dwells as flicker gave each dwell's mean 11 counts for 4.6)."""
    av, power = channel.allan, (0, 1)
    x, chi2, jac = _reweighted(av, channel.dt, 1, power=power)
    free = len(power) + 2  # the band limit, N^2, q^2 and log T
    return ChannelNoise(channel.channel, av, _terms(x, _covariance(jac, chi2, av.tau_s.size, free), 1, ""),
                        _reduced(chi2, av.tau_s.size, free), channel.dt, float(x[0]))


def _terms(x: np.ndarray, cov: np.ndarray, n_gm: int, unit: str) -> tuple[Term, ...]:
    """Amplitudes from the fitted variances: value sqrt(v), u = u(v) / (2
    sqrt(v)) where v exceeds 2 u(v), else sqrt(v + u(v)) (an upper bound
    for a term the data do not show); dof 2 (v / u(v))^2 / 4 = the chi-square
    dof of a variance estimate of that relative uncertainty, halved for the
    square root (at least 1)."""
    units = {"quantization": f"{unit} s", "white_density": f"{unit} sqrt(s)", "bias_instability": unit,
             "random_walk": f"{unit} / sqrt(s)", "gauss_markov_sd": unit, "gauss_markov_tau_s": "s"}
    out = []

    def amplitude(name: str, index: int, k: int) -> None:
        v, uv = float(x[k]), float(math.sqrt(max(cov[k, k], 0.0)))
        if uv > 0 and v > 2 * uv:
            value, u, dof = math.sqrt(v), uv / (2 * math.sqrt(v)), max(2 * (v / uv) ** 2 / 4, 1.0)
        else:  # not shown by the data: an upper bound, with the least dof
            value, u, dof = math.sqrt(max(v, 0.0)), math.sqrt(max(v, 0.0) + uv), 1.0
        out.append(Term(name, index, value, u, min(dof, 1e6), units[name]))

    for k, name in enumerate(POWER_TERMS):
        amplitude(name, 0, k)
    order: list[int] = [int(k) for k in np.argsort(x[4 + n_gm:4 + 2 * n_gm])] if n_gm else []
    for j, g in enumerate(order):
        amplitude("gauss_markov_sd", j, 4 + int(g))
        k = 4 + n_gm + int(g)
        t, ut = math.exp(x[k]), math.exp(x[k]) * math.sqrt(max(cov[k, k], 0.0))
        out.append(Term("gauss_markov_tau_s", j, t, ut, min(max(0.5 * (t / ut) ** 2, 1.0), 1e6) if ut > 0 else 1.0,
                        units["gauss_markov_tau_s"]))
    return tuple(out)


def identify_channel(channel: str, pieces: list[np.ndarray], fs_hz: float, unit: str,
                     first: AllanVariance | None = None, sizes: list[int] | None = None) -> ChannelNoise:
    """The Allan variance of a channel's residual pieces (``first``, when
    already computed: ``allan.pooled_avars``; then ``sizes``, the pieces'
    lengths, may stand for the pieces), its edf for the noise type of its
    own local slope, and its fitted model."""
    first = pooled_avar(pieces, fs_hz) if first is None else first
    sizes = [p.size for p in pieces] if sizes is None else sizes
    return fit_channel(channel, with_edf(first, sizes, _alphas(first.tau_s, first.avar), fs_hz), 1 / fs_hz, unit)
