"""What a real logger does to the time base, for the simulator: lost samples
and packets, records written twice, stamps that repeat, stamp jitter and a
clock that drifts against the table. ``rotcal.timebase.check`` finds and repairs
these; the realised sizes go to ``truth.json``.

The logger samples regularly on its own clock: with ``clock_drift_ppm`` = d
its clock runs fast by d, so a sample taken at table time t is stamped
t (1 + d 1e-6). Jitter is noise on the stamps only (the sampling stays
regular), Gaussian with ``jitter_s`` standard deviation.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import numpy as np
import polars as pl

from rotcal.errors import ConfigError


@dataclass(frozen=True)
class TimebaseDefects:
    """The defects to simulate; all off by default."""

    drop_fraction: float = 0.0           # samples lost independently
    gap_count: int = 0                   # lost packets: runs of gap_s without samples
    gap_s: float = 2.0
    duplicate_fraction: float = 0.0      # records written twice (same stamp, same values)
    repeat_stamp_fraction: float = 0.0   # a sample stamped with its predecessor's stamp
    jitter_s: float = 0.0                # standard deviation of the stamps' noise
    clock_drift_ppm: float = 0.0         # logger clock fast against the table

    @property
    def clock_factor(self) -> float:
        return 1.0 + self.clock_drift_ppm * 1e-6

    def checked(self) -> TimebaseDefects:
        for f in fields(self):  # comparisons below would raise TypeError for text, and pass NaN
            value = getattr(self, f.name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not -1e300 < value < 1e300 or value != value:
                raise ConfigError(f"timebase: {f.name} = {value!r} must be a finite number")
        if not isinstance(self.gap_count, int):
            raise ConfigError(f"timebase: gap_count = {self.gap_count!r} must be a whole number")
        for name in ("drop_fraction", "duplicate_fraction", "repeat_stamp_fraction"):
            if not 0.0 <= getattr(self, name) < 0.5:
                raise ConfigError(f"timebase: {name} = {getattr(self, name)} must be in [0, 0.5)")
        if self.jitter_s < 0 or self.gap_s <= 0 or self.gap_count < 0:
            raise ConfigError("timebase: jitter_s, gap_count must be >= 0 and gap_s > 0")
        return self


def apply_defects(samples: pl.DataFrame, defects: TimebaseDefects, rng: np.random.Generator) -> tuple[pl.DataFrame, dict]:
    """Stamp ``samples`` (table time in ``t_ns``) as the logger would.

    Returns the written rows (stamps in ``t_ns``) and the realised sizes.
    """
    n = samples.height
    t_ns = samples["t_ns"].to_numpy()
    dt_ns = float(np.median(np.diff(t_ns))) if n > 1 else 1.0
    keep = rng.random(n) >= defects.drop_fraction
    dropped = int((~keep).sum())
    gap_len = int(round(defects.gap_s * 1e9 / dt_ns))
    in_gap = np.zeros(n, bool)
    for start in rng.integers(0, max(n - gap_len, 1), defects.gap_count):
        in_gap[start : start + gap_len] = True
    keep &= ~in_gap
    if not keep.any():
        raise ConfigError(f"timebase: {defects.gap_count} gaps of {defects.gap_s:g} s leave no sample of the recording")
    stamps = np.round(t_ns * defects.clock_factor + rng.standard_normal(n) * defects.jitter_s * 1e9).astype(np.int64)
    # the logger's clock starts at 0: jitter never stamps a sample before it (MCAP log times are unsigned)
    np.maximum(stamps, 0, out=stamps)
    rows = samples.with_columns(t_ns=pl.Series(stamps)).filter(pl.Series(keep))
    stamps = rows["t_ns"].to_numpy()
    # a repeated stamp copies the last stamp that was not itself repeated
    repeat = rng.random(rows.height) < defects.repeat_stamp_fraction
    repeat[0] = False
    source = np.maximum.accumulate(np.where(repeat, 0, np.arange(rows.height)))
    rows = rows.with_columns(t_ns=pl.Series(stamps[source]))
    twice = rng.random(rows.height) < defects.duplicate_fraction
    rows = rows[np.repeat(np.arange(rows.height), np.where(twice, 2, 1))]
    realised = {
        **asdict(defects),
        "dropped_samples": dropped,
        "gap_samples": int(in_gap.sum()),
        "missing_samples": int(n - keep.sum()),
        "repeated_stamps": int(repeat.sum()),
        "duplicated_records": int(twice.sum()),
        "jitter_realised_s": float(np.std(stamps - np.round(t_ns[keep] * defects.clock_factor))) / 1e9,
    }
    return rows, realised
