"""``rotcal apply``: a calibration applied to a recording.

The recording is read as every rotcal input is (``ingest.dataset.load_dataset``:
any capture form, with its ``dataset.toml``), corrected with the chosen
rate's a = P (R - O) (Geist 2017 Eq. 18) and written with the stamps it
had, in the calibration's frame."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rotcal.apply.correct import correct, correction_covariance
from rotcal.apply.files import Calibrated, file_metadata, output_format, write_calibrated
from rotcal.errors import InputError
from rotcal.model.calibration import Calibration
from rotcal.model.physics import CHANNELS


@dataclass(frozen=True)
class Applied:
    """What ``rotcal apply`` did: the file written, the samples, the rate and
    frame of the calibration used, and notes on the recording."""

    path: Path
    samples: int
    rate_hz: float
    frame: str
    notes: tuple[str, ...]


def writable_file(path: Path) -> Path:
    """``path`` if a file can be written there (its folder exists and may be
    written, it is not itself a directory); checked before any work."""
    if path.is_dir():
        raise InputError("output is a directory: give a file name", path=path)
    folder = path.parent
    if not folder.is_dir():
        raise InputError(f"output folder {folder} does not exist", path=path)
    if not os.access(folder, os.W_OK | os.X_OK):
        raise InputError(f"output folder {folder} cannot be written", path=path)
    return path


def calibrated(raw: np.ndarray, t_ns: np.ndarray, cal: Calibration, rate_hz: float | None, recording: str,
               source: str, uncertainty: bool) -> Calibrated:
    """The calibrated samples of ``raw`` (3 x n, output units) with the
    chosen rate's correction and, when asked, their covariance."""
    rc = cal.rate(rate_hz)
    cov = correction_covariance(raw, rc) if uncertainty else None
    return Calibrated(t_ns, correct(raw, rc.P_matrix, rc.O_vector), cov,
                      file_metadata(recording, f"{cal.dataset} ({source})", rc.rate_hz, rc.frame, rc.model, uncertainty))


def apply_calibration(calibration: Path, recording: Path, out: Path, rate_hz: float | None = None,
                      uncertainty: bool = False, meta: Path | None = None) -> Applied:
    """Apply ``calibration`` (calibration.json, or a run's output directory)
    to ``recording`` (a dataset directory or capture file; ``meta`` its
    dataset.toml kept elsewhere) and write the result to ``out``.

    The recording's output unit must be the calibration's where its
    dataset.toml names one. Raises ``InputError`` for a bad calibration,
    recording or output path."""
    from rotcal.ingest.dataset import load_dataset

    output_format(out)
    writable_file(out)
    cal = Calibration.read(calibration)
    cal.rate(rate_hz)  # a rate the calibration lacks is refused before the recording is read
    ds = load_dataset(recording, meta)
    if ds.meta.source is not None and ds.meta.output_unit != cal.output_unit:
        raise InputError(f"the recording's output unit is {ds.meta.output_unit!r} but the calibration's is "
                         f"{cal.output_unit!r}: apply a calibration of this device in the same unit",
                         path=ds.meta.source)
    raw = np.stack([ds.samples[c].cast(float).to_numpy() for c in CHANNELS])
    rec = calibrated(raw, ds.samples["t_ns"].to_numpy(), cal, rate_hz, ds.name, Path(calibration).name, uncertainty)
    path = write_calibrated(rec, out)
    rc = cal.rate(rate_hz)
    return Applied(path, raw.shape[1], rc.rate_hz, rc.frame, ds.notes)
