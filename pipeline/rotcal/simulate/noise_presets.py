"""Noise of real accelerometer classes, from their datasheets and published
Allan-variance analyses (sources in docs/simulate.md, "Noise presets"), in
physical units; ``SensorNoise.in_counts`` gives the simulator's
``NoiseSpec`` for a DUT of a given responsivity and sample rate.

Conventions (IEEE Std 952-1997 Annex C): a datasheet's noise density or
velocity random walk is taken as the white-noise coefficient N (Allan
variance N^2 / tau; VRW in m/s/sqrt(h) is N * 60); an "in-run bias
stability" quoted as the Allan deviation's minimum is B * 0.664, one quoted
by the IEEE convention is B itself (as each source says); a bias random walk
in m/s^3/sqrt(Hz) is K (Allan variance K^2 tau / 3).
"""

from __future__ import annotations

from dataclasses import dataclass

from rotcal.errors import ConfigError
from rotcal.simulate.noise import FLICKER_FLOOR, NoiseSpec

G0 = 9.80665  # m/s^2 per g (standard gravity: datasheets' g)
MICRO_G = 1e-6 * G0


@dataclass(frozen=True)
class SensorNoise:
    """A sensor class's noise: white density N ((m/s^2)/sqrt(Hz)), bias
    instability B (m/s^2), random walk K ((m/s^2)/sqrt(s)), the output's
    low-pass (-3 dB bandwidth Hz and order; 0: none) and its source."""

    name: str
    density: float
    bias_instability: float
    random_walk: float
    bandwidth_hz: float
    filter_order: int
    source: str

    def in_counts(self, counts_per_ms2: float, fs_hz: float) -> NoiseSpec:
        """The noise in output counts of a DUT of ``counts_per_ms2``
        sampled at ``fs_hz``: white sd N sqrt(fs); the low-pass kept where
        its bandwidth is below the Nyquist frequency (above it, the sampled
        output is white to Nyquist)."""
        cutoff = self.bandwidth_hz / fs_hz
        keep = self.filter_order > 0 and 0 < cutoff < 0.5
        return NoiseSpec(
            white_sd=self.density * counts_per_ms2 * fs_hz**0.5,
            lowpass_order=self.filter_order if keep else 0,
            lowpass_cutoff=cutoff if keep else 0.0,
            flicker_b=self.bias_instability * counts_per_ms2,
            random_walk_k=self.random_walk * counts_per_ms2,
        )


PRESETS = {p.name: p for p in (
    # consumer: Analog Devices ADXL345 datasheet Rev. G, Noise performance, Fig. 52 (Allan deviation):
    # 290 ug/sqrt(Hz) x, y (430 z); floor about 100 ug (resolution with long averaging)
    SensorNoise("adxl345", 290 * MICRO_G, 100 * MICRO_G / FLICKER_FLOOR, 0.0, 0.0, 0,
                "ADXL345 datasheet, Noise performance and Fig. 52"),
    # industrial MEMS IMU: Analog Devices ADIS16448 datasheet (VRW 0.11 m/s/sqrt(h), in-run bias stability 0.25 mg,
    # the Allan minimum); its random walk from the EuRoC MAV dataset's Kalibr model of the same sensor
    # (accelerometer_random_walk 3.0e-3 m/s^3/sqrt(Hz); noise density 2.0e-3, agreeing with the VRW)
    SensorNoise("adis16448", 0.11 / 60, 0.25e-3 * G0 / FLICKER_FLOOR, 3.0e-3, 0.0, 0,
                "ADIS16448 datasheet; EuRoC MAV dataset imu0 sensor.yaml (Burri et al. 2016)"),
    # AHRS module: Xsens MTi-1 series datasheet: noise density 120 ug/sqrt(Hz), in-run bias stability 0.03 mg
    # (Allan minimum), bandwidth 324 Hz
    SensorNoise("mti1", 120 * MICRO_G, 30 * MICRO_G / FLICKER_FLOOR, 0.0, 324.0, 2,
                "Xsens MTi 1-series datasheet (accelerometer table)"),
    # tactical-grade MEMS IMU: Inertial Sense IMX-6, 24 h static Allan deviation at 1 kHz: VRW 0.013 m/s/sqrt(h),
    # bias instability 2.8 ug by the IEEE convention (Allan minimum / 0.664)
    SensorNoise("imx6", 0.013 / 60, 2.8 * MICRO_G, 0.0, 0.0, 0,
                "Inertial Sense IMX-6 user manual, Allan deviation page"),
)}


def preset(name: str) -> SensorNoise:
    """The preset of that name, or a ConfigError listing them."""
    if name not in PRESETS:
        raise ConfigError(f"noise: unknown preset {name!r}; known: {', '.join(PRESETS)}")
    return PRESETS[name]
