"""A sensor's noise as real MEMS outputs make it: white, an autoregression,
a digital low-pass, Gauss-Markov (exponentially correlated) terms, flicker
(bias instability), random walk and output quantization, one channel at a
time, in output counts.

The terms and their coefficients are those of IEEE Std 952-1997 Annex C and
IEEE Std 1293-2018 (Allan-variance analysis): white noise density
N = white_sd / sqrt(fs) (Allan variance N^2 / tau), bias instability B (a
flicker floor, Allan deviation B sqrt(2 ln 2 / pi) = 0.664 B), random walk K
(Allan variance K^2 tau / 3), and first-order Gauss-Markov terms of
correlation time T_c and stationary sd q_c.

Flicker is drawn as a sum of Gauss-Markov terms with correlation times
spaced two per decade from the sample interval to the recording's length,
each of variance B^2 ln(r) / pi (r = sqrt(10) the spacing): their summed
two-sided power spectral density is B^2 / (2 pi f) within the band (the
sum of Lorentzians log-spaced in corner frequency is 1/f to +-0.4 dB at two
per decade). Chosen over spectral shaping by FFT because it is causal, runs
on a time grid with the logger's pauses in it, has no circular wrap-around
of a periodic FFT series, and is exact in discrete time (each term's
transition exp(-dt/T_c)), so the drawn process is what the Allan model says
at every averaging time inside the band; its floor is physically bounded
(every real flicker has a corner below 1/duration).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.signal import butter, lfilter, sosfilt

from rotcal.errors import ConfigError

FLICKER_PER_DECADE = 2
# the Allan deviation of flicker over its coefficient B: sqrt(2 ln 2 / pi) (IEEE Std 952 C.6)
FLICKER_FLOOR = math.sqrt(2 * math.log(2) / math.pi)


@dataclass(frozen=True)
class NoiseSpec:
    """One channel's noise, in output counts and seconds.

    ``white_sd``: sd of the white noise per sample (at the low-pass's input);
    ``ar``: autoregression coefficients a_1..a_p (x_k = sum a_i x_{k-i} + e_k)
    and ``ar_sd`` the autoregression's stationary sd; ``lowpass_order`` and
    ``lowpass_cutoff`` (a fraction of the sample rate, below 0.5): a
    Butterworth filter of the white and autoregressive parts (unit gain at
    0 Hz, so their density below the cutoff is unchanged);
    ``gauss_markov``: (correlation time s, stationary sd) per term;
    ``flicker_b``: bias instability B (IEEE Std 952); ``random_walk_k``:
    random walk K (counts / sqrt(s)); ``quantization``: the output's step
    (counts; 0 leaves the DUT's own integer rounding).
    """

    white_sd: float = 0.0
    ar: tuple[float, ...] = ()
    ar_sd: float = 0.0
    lowpass_order: int = 0
    lowpass_cutoff: float = 0.0
    gauss_markov: tuple[tuple[float, float], ...] = ()
    flicker_b: float = 0.0
    random_walk_k: float = 0.0
    quantization: float = 0.0

    def checked(self) -> NoiseSpec:
        """The spec, or a ConfigError naming the first value no noise can have."""
        for name in ("white_sd", "ar_sd", "flicker_b", "random_walk_k", "quantization", "lowpass_cutoff"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise ConfigError(f"noise: {name} = {value!r} must be a finite number >= 0")
        if not isinstance(self.lowpass_order, int) or isinstance(self.lowpass_order, bool) or not 0 <= self.lowpass_order <= 8:
            raise ConfigError(f"noise: lowpass_order = {self.lowpass_order!r} must be a whole number from 0 to 8")
        if self.lowpass_order and not 0 < self.lowpass_cutoff < 0.5:
            raise ConfigError(f"noise: lowpass_cutoff = {self.lowpass_cutoff!r} must be between 0 and 0.5 of the sample rate")
        if not all(isinstance(a, int | float) and math.isfinite(a) for a in self.ar):
            raise ConfigError(f"noise: ar = {list(self.ar)!r} must be a list of numbers")
        if self.ar and np.any(np.abs(np.roots([1.0, *(-np.asarray(self.ar, float))])) >= 1):
            raise ConfigError(f"noise: ar = {list(self.ar)!r} is not stationary (a root of the AR polynomial on or outside the unit circle)")
        for term in self.gauss_markov:
            if (len(term) != 2 or not all(isinstance(v, int | float) and math.isfinite(v) for v in term)
                    or term[0] <= 0 or term[1] < 0):
                raise ConfigError(f"noise: gauss_markov term {list(term)!r} must be [tau_s > 0, sd >= 0]")
        return self

    def is_white(self) -> bool:
        """Only white noise (or none): the DUT's own noise needs no more."""
        return self == NoiseSpec(white_sd=self.white_sd)


def ar_response(ar: tuple[float, ...]) -> np.ndarray:
    """The impulse response of the autoregression 1 / (1 - sum a_i z^-i),
    until it is below 1e-16 of its start (at most 4M samples)."""
    n = 64
    while True:
        impulse = np.zeros(n)
        impulse[0] = 1.0
        h = lfilter([1.0], [1.0, *(-np.asarray(ar, float))], impulse)
        if np.max(np.abs(h[-8:])) < 1e-16 or n >= 1 << 22:
            return h
        n *= 4


def ar_innovation_sd(ar: tuple[float, ...], stationary_sd: float) -> float:
    """The innovation sd of an AR(p) process of the given stationary sd:
    sigma_e^2 = gamma_0 / sum h_k^2, h the impulse response (Box & Jenkins 3.2)."""
    if not ar or stationary_sd == 0:
        return stationary_sd
    h = ar_response(ar)
    return stationary_sd / math.sqrt(float(h @ h))


def flicker_terms(b: float, duration_s: float, fs_hz: float) -> tuple[tuple[float, float], ...]:
    """The Gauss-Markov terms (tau_s, sd) whose sum is flicker of bias
    instability ``b`` from the sample interval to ``duration_s`` (module docstring)."""
    if b == 0:
        return ()
    r = 10 ** (1 / FLICKER_PER_DECADE)
    decades = max(math.log10(max(duration_s * fs_hz, 1.0)), 1 / FLICKER_PER_DECADE)
    taus = (1 / fs_hz) * r ** np.arange(round(decades * FLICKER_PER_DECADE) + 1)
    sd = b * math.sqrt(math.log(r) / math.pi)
    return tuple((float(t), sd) for t in taus)


def _gauss_markov(terms: tuple[tuple[float, float], ...], n: int, fs_hz: float, rng: np.random.Generator) -> np.ndarray:
    """The sum of first-order Gauss-Markov terms, exact in discrete time
    (x_k = a x_{k-1} + sd sqrt(1 - a^2) e_k, a = exp(-dt/T_c)), each started
    in its stationary state."""
    if not terms:
        return np.zeros(n)
    tau, sd = (np.asarray(v, float) for v in zip(*terms))
    a = np.exp(-1.0 / (fs_hz * tau))
    e = rng.standard_normal((tau.size, n)) * (sd * np.sqrt(1 - a**2))[:, None]
    e[:, 0] = rng.standard_normal(tau.size) * sd  # the stationary start
    out = np.zeros(n)
    for k in range(tau.size):  # one recursion per term, each vectorized over time by lfilter
        out += lfilter([1.0], [1.0, -a[k]], e[k])
    return out


def draw(spec: NoiseSpec, n: int, fs_hz: float, rng: np.random.Generator) -> np.ndarray:
    """One channel's noise (counts), ``n`` samples at ``fs_hz``, rounded to
    ``quantization`` when it is set (a noise-only output); the same
    generator state gives the same numbers."""
    return quantized(draw_channels(spec, n, fs_hz, rng, 1)[:, 0], spec.quantization)


def draw_channels(spec: NoiseSpec, n: int, fs_hz: float, rng: np.random.Generator, channels: int) -> np.ndarray:
    """``channels`` independent draws of the noise before quantization,
    (n, channels); each channel's terms are drawn in turn from ``rng``."""
    spec = spec.checked()
    out = np.empty((n, channels))
    sigma_e = ar_innovation_sd(spec.ar, spec.ar_sd)
    # the filters' start-up transients are drawn and dropped: the noise is stationary from its first sample
    burn_ar = ar_response(spec.ar).size if spec.ar_sd and spec.ar else 0
    burn_lp = math.ceil(20 / spec.lowpass_cutoff) if spec.lowpass_order else 0
    sos = butter(spec.lowpass_order, 2 * spec.lowpass_cutoff, output="sos") if spec.lowpass_order else None
    terms = spec.gauss_markov + flicker_terms(spec.flicker_b, n / fs_hz, fs_hz)
    for c in range(channels):
        x = spec.white_sd * rng.standard_normal(n + burn_lp)
        if spec.ar_sd:
            e = rng.standard_normal(n + burn_lp + burn_ar) * sigma_e
            x += lfilter([1.0], [1.0, *(-np.asarray(spec.ar, float))], e)[burn_ar:]
        if sos is not None:
            x = sosfilt(sos, x)
        x = x[burn_lp:] + _gauss_markov(terms, n, fs_hz, rng)
        if spec.random_walk_k:
            x += np.cumsum(rng.standard_normal(n)) * spec.random_walk_k / math.sqrt(fs_hz)
        out[:, c] = x
    return out


def quantized(x: np.ndarray, step: float) -> np.ndarray:
    """The output rounded to multiples of ``step`` counts (unchanged for 0)."""
    return x if step == 0 else np.round(x / step) * step + 0.0  # + 0.0: no negative zeros


def noise_terms(spec: NoiseSpec, fs_hz: float) -> dict:
    """The drawn noise's IEEE Std 952 terms (counts, seconds): the white
    density N of everything white below the low-pass (the white part and the
    autoregression's density at 0 Hz, sigma_e / (1 - sum a)), B, K, the
    Gauss-Markov terms, the quantization step; what the noise
    identification should find."""
    sigma_e = ar_innovation_sd(spec.ar, spec.ar_sd)
    density_ar = sigma_e / (1 - sum(spec.ar)) if spec.ar else sigma_e
    step_white = spec.quantization / math.sqrt(12)  # a step well below the noise adds white noise of step/sqrt(12)
    return {
        "white_density": math.sqrt((spec.white_sd**2 + density_ar**2 + step_white**2) / fs_hz),
        "bias_instability": spec.flicker_b,
        "random_walk": spec.random_walk_k,
        "gauss_markov": [list(t) for t in spec.gauss_markov],
        "quantization": spec.quantization,
    }
