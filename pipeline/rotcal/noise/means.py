"""The covariance of the noise's means over time windows (segments, poses)
under a channel's identified noise model (``noise.model``), the IEEE Std
952 terms taken as processes in time:

- white noise of density N: a window of length L averages it to variance
  N^2 / L, and disjoint windows are uncorrelated;
- a first-order Gauss-Markov term of sd q and correlation time T
  (autocovariance q^2 exp(-|t| / T));
- flicker of bias instability B: the sum of Gauss-Markov terms with
  correlation times two per decade from the sample interval to the record's
  length, each of variance B^2 ln(r) / pi (r = sqrt(10)), whose summed
  spectral density is B^2 / (2 pi f) within that band (as
  ``simulate.noise`` draws it). A flicker slower than the record is the
  offset itself for this record; the band's lower end is the record's
  length, so each window's mean carries the flicker the record cannot
  average, and windows far apart share it;
- random walk of coefficient K, from the record's first sample (variance
  K^2 t at time t after it: the offset is the sensor's at the start).

The covariance of two windows' means of a stationary term of
autocovariance k is (1 / (L_a L_b)) times the double integral of k(s - t),
Phi(b1 - a0) - Phi(b1 - a1) - Phi(b0 - a0) + Phi(b0 - a1) with Phi the
even second antiderivative of k (Phi'' = k, Phi(0) = Phi'(0) = 0):
Phi(x) = T^2 (|x| / T - 1 + exp(-|x| / T)) for exp(-|x| / T).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from rotcal.noise.model import FLICKER, ChannelNoise, bounded_channel, free_parameters, gauss_markov_avar

FLICKER_PER_DECADE = 2
# the averaging times that decide whether a noise slower than white is shown: the longest five octaves
SLOW_OCTAVES = 5


@dataclass(frozen=True)
class NoiseProcess:
    """One channel's noise terms as processes (counts, seconds): white
    density ``white_density`` (N), Gauss-Markov terms ``gauss_markov``
    ((T, q) each), bias instability ``flicker_b`` (B), random walk
    ``random_walk_k`` (K)."""

    white_density: float = 0.0
    gauss_markov: tuple[tuple[float, float], ...] = ()
    flicker_b: float = 0.0
    random_walk_k: float = 0.0


def flicker_terms(b: float, dt_s: float, duration_s: float) -> tuple[tuple[float, float], ...]:
    """Flicker of bias instability ``b`` as Gauss-Markov terms (T, q) from
    ``dt_s`` to ``duration_s`` (module docstring)."""
    if b <= 0 or dt_s <= 0:
        return ()
    r = 10 ** (1 / FLICKER_PER_DECADE)
    decades = max(math.log10(max(duration_s / dt_s, 1.0)), 1 / FLICKER_PER_DECADE)
    taus = dt_s * r ** np.arange(round(decades * FLICKER_PER_DECADE) + 1)
    q = b * math.sqrt(math.log(r) / math.pi)
    return tuple((float(t), q) for t in taus)


def _phi_exponential(x: np.ndarray, t: float) -> np.ndarray:
    """T^2 (u - 1 + exp(-u)), u = |x| / T, without cancellation for small u."""
    u = np.abs(x) / t
    small = u < 1e-4
    return t * t * np.where(small, u * u / 2 - u**3 / 6 + u**4 / 24, u + np.expm1(-np.where(small, 0.0, u)))


def _window_integral(phi, a0: np.ndarray, a1: np.ndarray) -> np.ndarray:
    """The double integral over every pair of windows [a0_i, a1_i] x [a0_j, a1_j] from Phi."""
    return (phi(a1[None, :] - a0[:, None]) - phi(a1[None, :] - a1[:, None]) - phi(a0[None, :] - a0[:, None])
            + phi(a0[None, :] - a1[:, None]))


def window_mean_covariance(process: NoiseProcess, start_s: np.ndarray, stop_s: np.ndarray, dt_s: float,
                           record_s: tuple[float, float]) -> np.ndarray:
    """The covariance (windows x windows) of the noise's means over the
    windows [start_s, stop_s] (s, on the record's clock), under
    ``process`` sampled every ``dt_s`` over the record ``record_s`` (first
    and last sample's times)."""
    a0 = np.asarray(start_s, float)
    a1 = np.maximum(np.asarray(stop_s, float), a0 + dt_s)  # a window holds at least one sample interval
    length = a1 - a0
    norm = np.outer(length, length)
    out = np.zeros(norm.shape)
    terms = process.gauss_markov + flicker_terms(process.flicker_b, dt_s, record_s[1] - record_s[0])
    for t, q in terms:
        if q > 0 and t > 0:
            out += q * q * _window_integral(lambda x, t=t: _phi_exponential(x, t), a0, a1) / norm
    if process.random_walk_k > 0:
        # min(s, t) = (s + t - |s - t|) / 2 from the record's start; Phi for |x| is |x|^3 / 6
        s0, s1 = a0 - record_s[0], a1 - record_s[0]
        centre = (s0 + s1) / 2
        spread = _window_integral(lambda x: np.abs(x) ** 3 / 6, s0, s1) / norm
        out += process.random_walk_k**2 * ((centre[:, None] + centre[None, :]) / 2 - spread / 2)
    # white noise: N^2 / L on the diagonal (disjoint windows share none of it)
    out[np.diag_indices_from(out)] += process.white_density**2 / length
    return out


def slow_shown(channel: ChannelNoise) -> bool:
    """Whether the channel's Allan variance over its longest averaging
    times (the last ``SLOW_OCTAVES`` octaves) rises above what its fast
    terms give there (white density N^2 / tau and the Gauss-Markov terms
    shorter than those times: a filter's, an autoregression's) by more than
    2 standard deviations, pooled (each estimate's sd sigma^2 sqrt(2 / edf),
    NIST SP 1065 5.3): the data show a noise slower than those terms,
    whichever terms the fit split it into."""
    av = channel.allan
    if av.tau_s.size == 0 or not channel.terms:
        return False
    last = slice(max(av.tau_s.size - SLOW_OCTAVES, 0), None)
    tau, avar, edf = av.tau_s[last], av.avar[last], av.edf[last]
    fast = _fast(channel, float(tau[0]))
    expected = fast.white_density**2 / tau
    for t, q in fast.gauss_markov:
        expected = expected + gauss_markov_avar(tau, q, t, channel.dt)
    z = (avar - expected) / (avar * np.sqrt(2 / np.maximum(edf, 1e-9)))
    return bool(np.sum(z) / np.sqrt(z.size) > 2.0)


def _fast(channel: ChannelNoise, shortest_s: float) -> NoiseProcess:
    """The channel's white density and Gauss-Markov terms shorter than ``shortest_s``."""
    value = {(t.term, t.index): t.value for t in channel.terms}
    gm = tuple((value[("gauss_markov_tau_s", j)], value[("gauss_markov_sd", j)]) for j in range(len(channel.terms))
               if ("gauss_markov_sd", j) in value and ("gauss_markov_tau_s", j) in value)
    return NoiseProcess(value.get(("white_density", 0), 0.0), tuple(t for t in gm if t[0] < shortest_s))


def process_of(channel: ChannelNoise) -> NoiseProcess:
    """A channel's process from its identified terms (``noise.model``) at
    their fitted values, without the random walk: identified within
    segments, a random walk cannot be told from a Gauss-Markov term longer
    than they are, and extrapolated over the record it would widen a
    bounded wander without limit (the offsets' scatter between segments
    measures it, ``fit.wander``). Flicker and a slow Gauss-Markov term share
    the low frequencies, each uncertain, their sum not: they are kept at
    their fitted values where the longest averaging times show a noise
    slower than white (``slow_shown``), else only the Gauss-Markov terms
    shorter than those times (a filter's or an autoregression's)."""
    if slow_shown(channel):
        return replace(_fast(channel, np.inf), flicker_b=_value(channel, "bias_instability"))
    av = channel.allan
    return _fast(channel, float(av.tau_s[max(av.tau_s.size - SLOW_OCTAVES, 0)]) if av.tau_s.size else 0.0)


def _value(channel: ChannelNoise, term: str) -> float:
    return next((t.value for t in channel.terms if t.term == term and t.index == 0), 0.0)



def short_record_process(channel: ChannelNoise, fast_below_s: float) -> NoiseProcess:
    """A channel's process identified from pieces too short for
    ``slow_shown``'s longest octaves to pass a filter's or an
    autoregression's correlation time (a static pose's few seconds of
    averaging): its white density and Gauss-Markov terms shorter than
    ``fast_below_s`` (their share of each piece's scatter), and the slower
    terms (flicker, Gauss-Markov) where the data show them: each beyond
    its standard uncertainty (``model._terms``), or, where the fit split
    them so that none is alone (flicker beside a random walk), all at their
    fitted values where ``slow_shown`` and their Allan variance at the
    longest averaging time exceeds the fast terms' (below it the fit could
    have given them a fast term's tail). Where the averaging times are too
    few for the model to have tried a Gauss-Markov term, that slow part is
    white noise and one Gauss-Markov term fitted alone
    (``model.bounded_channel``): a bounded process, the scatter between
    poses measuring any slower rest. The random walk is left out, as
    ``process_of`` leaves it."""
    value = {(t.term, t.index): t for t in channel.terms}
    fast = _fast(channel, fast_below_s)
    slow = [((value[("gauss_markov_tau_s", j)].value, sd.value), sd) for (term, j), sd in value.items()
            if term == "gauss_markov_sd" and value[("gauss_markov_tau_s", j)].value >= fast_below_s]
    flicker = value.get(("bias_instability", 0))
    shown = replace(fast, gauss_markov=fast.gauss_markov + tuple(t for t, sd in slow if sd.value > sd.u),
                    flicker_b=flicker.value if flicker is not None and flicker.value > flicker.u else 0.0)
    if shown != fast or not slow_shown(channel) or not channel.allan.tau_s.size:
        return shown
    tau = channel.allan.tau_s[-1:]
    fast_avar = fast.white_density**2 / tau + sum(gauss_markov_avar(tau, q, t, channel.dt) for t, q in fast.gauss_markov)
    slow_avar = (FLICKER * _value(channel, "bias_instability") ** 2 + sum(gauss_markov_avar(tau, q, t, channel.dt) for (t, q), _ in slow) + _value(channel, "random_walk") ** 2 * tau / 3)
    if float(slow_avar[0]) <= float(fast_avar[0]):
        return fast
    if channel.allan.tau_s.size <= free_parameters(1):  # too few for ``model`` to try a Gauss-Markov term
        return _fast(bounded_channel(channel), np.inf)
    return replace(fast, gauss_markov=fast.gauss_markov + tuple(t for t, _ in slow), flicker_b=_value(channel, "bias_instability"))
