"""Selected extensions tested against the noise's measured spectrum.

The forward selection scores an extension by the chi-square it removes,
taking the (whitened) residuals as white. A noise whose density is above
white at the frequencies where an effect's signature lies (a wander under
a slow rotation's harmonics, a sensor filter's pass band) makes that
chi-square too large: least squares on a regressor has the variance white
noise of the density at the regressor's frequencies would give (Grenander
1954), so under the noise the statistic's null mean is the density's ratio
to white averaged over the signature's spectrum,

    F_eff = sum_j |D_j|^2 F(f_j) / sum_j |D_j|^2,

D_j the Fourier coefficients of the signature within each segment (the
residuals' change when the extension is dropped and the rest refitted),
F(f) the density ratio read from the residuals' periodograms pooled on one
frequency axis (``fit.spectrum.density_ratio_at``: 1 where white noise
explains them, so white noise keeps every test as it was). Each selected
catalogue extension is tested again with chi^2 / F_eff per channel, on its
parameter count, at the diagnosis's false-alarm rate: where the noise
explains it, it is dropped and its row says so with the density's size;
where not, the row says the evidence favours the effect over the noise.
"""

from __future__ import annotations

import numpy as np

from rotcal.diagnose.candidates import STEP, Candidate
from rotcal.diagnose.fitting import ModelFit, chi2_sf, without
from rotcal.diagnose.scans import p_is
from rotcal.fit.spectrum import band_index, density_ratio_at, periodogram
from rotcal.model.physics import CHANNELS


def _segments(fit: ModelFit) -> list[slice]:
    seg = fit.obs.segment
    edges = np.flatnonzero(np.r_[True, seg[1:] != seg[:-1], True])
    return [slice(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:]) if b - a >= 16]


class NoiseDensity:
    """The density ratio to white of the fit's (whitened) residuals, per
    channel, at any frequency: their segments' periodograms pooled."""

    def __init__(self, fit: ModelFit):
        m = fit.obs.motion
        self.parts = _segments(fit)
        self.dt = [float(np.median(np.diff(m.t_s[p]))) for p in self.parts]
        self.pooled: dict[int, tuple[np.ndarray, float]] = {}
        rates = fit.obs.rates[fit.obs.rate_idx]
        for part, dt in zip(self.parts, self.dt):
            n = part.stop - part.start
            gram = periodogram(fit.ev.resid[part], dt, abs(float(rates[part.start])) * n * dt if m.rotating[part.start] else 1.0)
            for k, sums, count in zip(gram.bands, gram.sums, gram.counts):
                old = self.pooled.get(int(k), (np.zeros(3), 0.0))
                self.pooled[int(k)] = (old[0] + sums, old[1] + float(count))
        self.cache: dict[tuple[int, int], np.ndarray] = {}

    @property
    def coloured(self) -> bool:
        return any(np.any(self.at(2.0 ** ((k + 0.5) / 4), 1.0) != 1.0) for k in self.pooled)

    def at(self, f_hz: float, low_hz: float) -> np.ndarray:
        """Each channel's ratio at ``f_hz`` (zero frequency: read below ``low_hz``)."""
        key = (int(band_index(np.array([f_hz]))[0]) if f_hz > 0 else -10**6, int(round(np.log2(low_hz) * 4)) if f_hz <= 0 else 0)
        if key not in self.cache:
            self.cache[key] = density_ratio_at(self.pooled, f_hz, low_hz)
        return self.cache[key]

    def effective(self, signature: np.ndarray) -> np.ndarray:
        """F_eff per channel of a signature (n, 3) in the residuals' domain."""
        num, den = np.zeros(3), np.zeros(3)
        for part, dt in zip(self.parts, self.dt):
            d = signature[part]
            n = d.shape[0]
            spectrum = np.abs(np.fft.rfft(d, axis=0)) ** 2
            energy = spectrum.sum(axis=0)
            if not np.any(energy > 0):
                continue
            bands = band_index(np.arange(1, spectrum.shape[0]) / (n * dt))
            ratio = np.empty_like(spectrum)
            ratio[0] = self.at(0.0, 1.0 / (n * dt))
            for k in np.unique(bands):
                ratio[1:][bands == k] = self.at(2.0 ** ((k + 0.5) / 4), 1.0 / (n * dt))
            num += (spectrum * ratio).sum(axis=0)
            den += energy
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)


def against_spectrum(final: ModelFit, alpha: float, only: tuple[Candidate, ...] = ()
                     ) -> tuple[ModelFit, dict[str, str]]:
    """The model with the catalogue extensions the noise's spectrum explains
    dropped (``only`` these where given), and per effect the sentence its
    diagnosis row adds (module docstring). Nothing changes where the
    residuals' spectrum is white."""
    texts: dict[str, str] = {}
    if not any(c != STEP for c in final.active):
        return final, texts
    density = NoiseDensity(final)
    if not density.coloured:
        return final, texts
    for cand in [c for c in final.active if c != STEP and (not only or c in only)]:
        reduced = without(final, (cand,))
        signature = reduced.ev.resid - final.ev.resid
        f_eff = density.effective(signature)
        chi2 = np.maximum(reduced.ev.rss - final.ev.rss, 0.0) / final.sigma**2
        if np.all(f_eff <= 1.0):
            continue
        stat = float(np.sum(chi2 / np.maximum(f_eff, 1.0)))
        k = len(cand.names)
        p = chi2_sf(stat, k)
        size = ("the noise's density at its signature's frequencies is "
                + ", ".join(f"{c} {v:.3g}" for c, v in zip(CHANNELS, f_eff)) + " times white")
        if p >= alpha:
            final = reduced
            text = (f"{cand.key} set aside: {size}, and that noise explains it "
                    f"(chi-square {stat:.1f} on {k} against the noise, {p_is(p)})")
        else:
            text = (f"for {cand.key} the evidence favours the effect over the noise ({size}; against the noise "
                    f"chi-square {stat:.1f} on {k}, {p_is(p)})")
        texts[cand.effect] = f"{texts[cand.effect]}; {text}" if cand.effect in texts else text
    return final, texts
