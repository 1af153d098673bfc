"""Segment fits' uncertainties from the measured noise (rotcal.fit.spectrum,
rotcal.fit.wander), checked by repeated simulation against the truth:
records of rotation segments about one table axis whose noise is drawn by
the simulator's noise model (rotcal.simulate.noise) over the whole record,
fitted by the fit stage (``fit_segments``)."""

from dataclasses import replace

import numpy as np
import polars as pl
import pytest

from rotcal.config import FitConfig
from rotcal.fit.segments import fit_segments, widened
from rotcal.fit.wander import NOT_MODELLED, SLOWER_THAN_RECORD, UNIDENTIFIED, wander_fit
from rotcal.noise.means import NoiseProcess, window_mean_covariance
from rotcal.simulate.noise import NoiseSpec, draw_channels

DT = 0.06
TRUTH = np.array([[100.0, 16000.0, -300.0], [-50.0, 200.0, 16000.0], [400.0, -100.0, 50.0]])


def record(noise: NoiseSpec, rates_hz: tuple[float, ...], n: int, rng: np.random.Generator) -> tuple[pl.DataFrame, pl.DataFrame]:
    """Samples and segments of one record: a rotation segment of ``n``
    samples at each rate in turn, the noise one process through them all."""
    k = len(rates_hz)
    theta = np.concatenate([360 * f * DT * np.arange(n) + 17.0 for f in rates_hz])
    clean = np.column_stack([np.ones(k * n), np.sin(np.radians(theta)), np.cos(np.radians(theta))]) @ TRUTH.T
    y = clean + draw_channels(noise, k * n, 1 / DT, rng, 3)
    samples = pl.DataFrame({"t_ns": np.arange(k * n, dtype=np.int64) * round(DT * 1e9), "u": y[:, 0], "v": y[:, 1], "w": y[:, 2],
                            "angle_deg": theta, "segment": np.repeat(np.arange(k), n).astype(np.int32)})
    segments = pl.DataFrame({"segment": np.arange(k, dtype=np.int32), "kind": ["rotation"] * k, "rate_hz": list(rates_hz),
                             "angle_source": ["commanded"] * k, "axis": ["x"] * k})
    return samples, segments


def normalised_errors(noise: NoiseSpec, rates_hz: tuple[float, ...], n: int, records: int, seed: int
                      ) -> tuple[np.ndarray, np.ndarray, list]:
    """(errors over the fits' standard uncertainties (records x segments,
    9), over the lag-based widening's, the fits)."""
    rng = np.random.default_rng(seed)
    z, z_lag, fits = [], [], []
    for _ in range(records):
        samples, segments = record(noise, rates_hz, n, rng)
        fitted = fit_segments(samples, segments, FitConfig(), workers=1)
        for f, rate in zip(fitted, rates_hz):
            error = (f.coef - TRUTH).ravel()
            z.append(error / np.sqrt(np.diag(f.cov)))
            white = replace(f, cov=white_covariance(f), spectrum=None, noise_ratio=None, offset_floor=None)
            z_lag.append(error / np.sqrt(np.diag(widened(white, 2 * np.pi * rate * DT).cov)))
        fits.append(fitted)
    return np.array(z), np.array(z_lag), fits


SINE = [1, 2, 4, 5, 7, 8]


def white_covariance(fit) -> np.ndarray:
    """A fit's covariance as the white-noise fit gave it (its measured noise taken out)."""
    ratio = np.ones((2, 3)) if fit.noise_ratio is None else fit.noise_ratio
    floor = np.zeros(3) if fit.offset_floor is None else fit.offset_floor
    cov = fit.cov.copy()
    cov[[0, 3, 6], [0, 3, 6]] -= floor**2
    scale = np.sqrt(np.column_stack([ratio[0], ratio[1], ratio[1]]).ravel())
    return cov / np.outer(scale, scale)


@pytest.mark.parametrize(("noise", "lag_fails"), [(NoiseSpec(white_sd=8.0, lowpass_order=2, lowpass_cutoff=0.1), True),
                                                 (NoiseSpec(white_sd=8.0, ar=(0.9,), ar_sd=8.0), False),
                                                 (NoiseSpec(white_sd=8.0, gauss_markov=((10.0, 4.0),)), True)])
def test_sine_terms_cover_coloured_noise(noise, lag_fails):
    """60 records of four segments (1200 samples at 0.05, 0.1, 0.2, 0.5 Hz):
    the sine terms' normalised errors have sd 0.8 to 1.25 per rate (1.0 to
    1.11), where the white-noise covariance gives up to 2.2 (low-pass at
    0.1 of the sample rate), 3.3 (autoregression 0.9) and 2.8 (wander of 4
    counts, 10 s). The lag-1/lag-2 widening (white plus a first-order
    autoregression) fitted the autoregression (1.0 to 1.23) but made the
    low-pass's uncertainties up to twice too large (0.56) and the
    wander's too small (2.26 at 0.05 Hz)."""
    rates = (0.05, 0.1, 0.2, 0.5)
    z, z_lag, fits = normalised_errors(noise, rates, 1200, 60, seed=11)
    sd = np.sqrt(np.mean(z.reshape(60, 4, 9)[:, :, SINE] ** 2, axis=(0, 2)))
    assert np.all((sd > 0.8) & (sd < 1.25)), sd
    ratio = np.array([f.noise_ratio[1] for record in fits for f in record]).reshape(60, 4, 3)
    z_white = z.reshape(60, 4, 9)[:, :, SINE] * np.sqrt(np.repeat(ratio, 2, axis=2))
    assert np.sqrt(np.mean(z_white**2, axis=(0, 2))).max() > 2.0
    sd_lag = np.sqrt(np.mean(z_lag.reshape(60, 4, 9)[:, :, SINE] ** 2, axis=(0, 2)))
    assert np.any((sd_lag < 0.8) | (sd_lag > 1.25)) == lag_fails, sd_lag


def group_mean_errors(noise: NoiseSpec, records: int, seed: int) -> tuple[np.ndarray, list]:
    """Records of eight 1200-sample segments, two at each of 0.05, 0.1,
    0.2, 0.5 Hz (576 s): each rate's offsets combined as the combine stage
    does (inverse-variance weighted mean of the two segments' C), their
    normalised errors (records x rates x channels), and the fits."""
    z, fits = normalised_errors(noise, (0.05, 0.1, 0.2, 0.5) * 2, 1200, records, seed)[::2]
    out = []
    for record in fits:
        error = np.array([f.coef[:, 0] - TRUTH[:, 0] for f in record]).reshape(2, 4, 3)
        var = np.array([np.diag(f.cov)[0::3] for f in record]).reshape(2, 4, 3)
        weight = (1 / var) / np.sum(1 / var, axis=0)
        out.append(np.sum(weight * error, axis=0) / np.sqrt(1 / np.sum(1 / var, axis=0)))
    return np.array(out), fits


def test_offsets_carry_a_slow_wander():
    """A Gauss-Markov wander of 4 counts with a time constant of 100 s
    under 8 counts of white noise, 30 records: each rate's combined offset
    has normalised errors of sd 0.75 to 1.25 and 90 to 99 % within 2 u
    (0.77, 97.5 %), and each fit says how large the floor it carries is
    (median 4.5 counts). Eight offsets leave the wander's variance seven
    contrasts: its posterior mean (``fit.wander.wander_fit``) leans to the
    conservative side here (0.84 with the likelihood's mode, which left the
    default plan's random-walk offsets at 89 % within 2 u)."""
    noise = NoiseSpec(white_sd=8.0, gauss_markov=((100.0, 4.0),))
    z, fits = group_mean_errors(noise, 30, seed=12)
    sd = np.sqrt(np.mean(z**2))
    assert 0.75 < sd < 1.25, sd
    assert 0.9 <= np.mean(np.abs(z) <= 2) <= 0.99
    floors = np.array([f.offset_floor for record in fits for f in record])
    assert 2.0 < np.median(floors) < 6.0, np.median(floors)
    assert {f.noise_note for record in fits for f in record} <= {None, SLOWER_THAN_RECORD}


def test_offsets_carry_the_flicker_floor():
    """Flicker of bias instability 2 counts under 8 counts of white noise
    (a floor of 1.3 counts in the Allan deviation), 30 records: its terms
    with time constants near the record's length move every segment's
    offset alike, so the scatter between segments does not show them; the
    noise model identified from the residuals does (rotcal.noise.means).
    Each rate's combined offset: normalised errors of sd 0.8 to 1.25 and 90 %
    or more within 2 u (1.02, 94 %), where the floor fitted to the scatter
    alone gave sd 1.74 (77 %); each offset's u is the flicker's (median
    2.3 counts), not 8 / sqrt(1200) = 0.23."""
    z, fits = group_mean_errors(NoiseSpec(white_sd=8.0, flicker_b=2.0), 30, seed=16)
    sd = np.sqrt(np.mean(z**2))
    assert 0.8 < sd < 1.25, sd
    assert np.mean(np.abs(z) <= 2) >= 0.9, np.mean(np.abs(z) <= 2)
    u = np.array([np.sqrt(np.diag(f.cov)[0::3]) for record in fits for f in record])
    assert 1.0 < np.median(u) < 4.0, np.median(u)


def test_a_wander_slower_than_the_record_is_flagged():
    """A time constant of 1000 s over a 576 s record: the wander's size is
    not identified; the fits that carry a floor say so."""
    _, _, fits = normalised_errors(NoiseSpec(white_sd=8.0, gauss_markov=((1000.0, 4.0),)), (0.05, 0.1, 0.2, 0.5) * 2,
                                   1200, 6, seed=15)
    flagged = [f.noise_note == SLOWER_THAN_RECORD for record in fits for f in record if f.offset_floor is not None]
    assert flagged and sum(flagged) >= len(flagged) / 2


def test_white_noise_leaves_the_fits_as_they_were():
    """White noise in 30 records of five segments: every fit's covariance is
    its white-noise one (no density ratio or offset floor significant)."""
    _, _, fits = normalised_errors(NoiseSpec(white_sd=8.0), (0.01, 0.05, 0.1, 0.2, 0.5), 1200, 30, seed=13)
    ratios = np.array([f.noise_ratio for record in fits for f in record])
    assert np.all(ratios == 1.0)
    assert all(f.offset_floor is None for record in fits for f in record)


def test_too_few_segments_say_the_floor_is_not_identified():
    """Three segments cannot separate a wander from the offsets' own noise:
    the fits carry the note instead of a floor."""
    _, _, fits = normalised_errors(NoiseSpec(white_sd=8.0, gauss_markov=((1000.0, 4.0),)), (0.1, 0.2, 0.5), 600, 1, seed=14)
    assert all(f.noise_note == UNIDENTIFIED.format(k=4) and f.offset_floor is None for f in fits[0])


def test_a_record_too_short_for_a_noise_model_is_widened_and_says_so():
    """Eight segments of 24 samples (1.4 s each) under a Gauss-Markov
    wander of 20 counts and 5 s: too few averaging times for a noise model,
    so each fit says so and the offsets' scatter gives the wander at its
    upper likelihood bound: the combined offset's u (each channel) is at
    least the sd of the wander's mean over the record (18 counts)."""
    samples, segments = record(NoiseSpec(white_sd=2.0, gauss_markov=((5.0, 20.0),)), (0.5,) * 8, 24, np.random.default_rng(1))
    fits = fit_segments(samples, segments, FitConfig(), workers=1)
    assert {f.noise_note for f in fits} == {NOT_MODELLED}
    u = 1 / np.sqrt(np.sum([1 / np.diag(f.cov)[0::3] for f in fits], axis=0))
    span = 8 * 24 * DT
    wander = np.sqrt(window_mean_covariance(NoiseProcess(gauss_markov=((5.0, 20.0),)), np.zeros(1), np.full(1, span), DT,
                                            (0.0, span))[0, 0])
    assert np.all(u >= wander), (u, wander)


def test_a_slow_rotation_reads_the_density_at_its_own_frequency():
    """Segments of 2.5 cycles at 0.01 Hz (4200 samples; beside one at 0.05
    Hz) under a wander of 110 s and sd 3.8 counts: the density at 0.01 Hz
    is 16 times the residuals' level, falling as 1/f^2 above it, and the
    record resolves almost nothing below it, so the mean ordinate of a
    window widened to gather its ordinates read it about 30 % low (the
    sine terms' sd of z was 1.22 at 0.01 Hz); the power law fitted to the
    window's bands gives the density at 0.01 Hz itself (0.94)."""
    noise = NoiseSpec(white_sd=8.0, gauss_markov=((110.0, 3.8),))
    z = normalised_errors(noise, (0.01, 0.05), 4200, 60, seed=5)[0].reshape(60, 2, 9)[:, :, SINE]
    sd = np.sqrt(np.mean(z**2, axis=(0, 2)))
    assert np.all((sd > 0.8) & (sd < 1.15)), sd


def test_the_wanders_size_is_its_posterior_mean():
    """Twelve offsets 1000 s apart scattering independently by 3 counts
    about one offset, each of its own noise 0.1 counts: at correlation times
    far below their spacing the restricted likelihood of the wander's
    variance s^2 is that of n - 1 = 11 independent residuals,
    L ~ (0.01 + s^2)^(-11/2) exp(-SS / (2 (0.01 + s^2))). The size taken
    is its mean under the log-uniform prior of the grid (about SS / 9 - 0.01,
    an inverse gamma's mean), here by quadrature: within 2 %, where the
    likelihood's mode, SS / 11 - 0.01, is 18 % below it (a variance from a
    dozen offsets leans to larger values)."""
    rng = np.random.default_rng(2)
    c = 40.0 + 3.0 * rng.standard_normal((12, 1))
    t = 1000.0 * np.arange(12)
    s2, _, tau = wander_fit(c, [np.eye(12) * 0.01], t, (1.0, 10.0), np.ones((12, 1)), t + 500.0)
    assert np.isfinite(tau)
    ss = float(np.sum((c - c.mean()) ** 2))
    spread = float(np.var(c, ddof=1))
    v = np.geomspace(1e-4 * spread, 100 * spread, 200_001)  # the grid's range, the prior log-uniform on it
    log_like = -5.5 * np.log(0.01 + v) - ss / (2 * (0.01 + v))
    like = np.exp(log_like - log_like.max())
    mean = float(np.sum(v * like) / np.sum(like))  # sums over a log-spaced grid: the prior dv / v
    assert abs(s2[0] / mean - 1) < 0.02, (s2[0], mean)
    assert (ss / 11 - 0.01) / mean < 0.85


def test_a_mild_filter_is_read_at_zero_frequency():
    """A second-order Butterworth low-pass at 0.4 of the sample rate passes
    white noise's density unchanged below its corner and removes a fifth of
    its variance above: the offsets' density ratio to the residuals' mean
    square is 1 / mean |H|^2 = 1.27 (the filter's response, scipy), which
    the zero-frequency window's 8 to 64 ordinates cannot tell from white
    noise at 1e-3 (they took F = 1 in 80 % of the fits, u 11 % short); a
    window of 512 does. Ten records of four segments: F at least 0.95 of
    1.27 in 90 % of the fits (1.25 at the tenth percentile), median 1.44
    (the larger of the narrow window's noisy mean and the wide one's)."""
    from scipy.signal import butter, sosfreqz

    _, response = sosfreqz(butter(2, 0.8, output="sos"), worN=100_000)
    truth = 1 / np.mean(np.abs(response) ** 2)
    assert 1.26 < truth < 1.28
    _, _, fits = normalised_errors(NoiseSpec(white_sd=8.0, lowpass_order=2, lowpass_cutoff=0.4), (0.05, 0.1, 0.2, 0.5),
                                   1200, 10, seed=17)
    zero = np.array([f.noise_ratio[0] for record in fits for f in record])
    assert np.percentile(zero, 10) > 0.95 * truth, np.percentile(zero, 10)
    assert np.median(zero) < 1.25 * truth, np.median(zero)
