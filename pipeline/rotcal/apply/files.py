"""Write a calibrated recording: Parquet, CSV or MCAP by the file's suffix,
atomically (a temporary file beside the target, renamed over it once whole).

Every form holds the time and a_x, a_y, a_z (m/s^2, the calibration's
frame) and, when asked, each sample's uncertainty; the frame and the
calibration they come from are in the file's metadata: Parquet key-value
metadata, ``#`` comment lines at the top of the CSV, the Imu messages'
``header.frame_id`` and the MCAP channel's metadata.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq

from rotcal import __version__
from rotcal.apply.correct import full_covariance, standard_uncertainty
from rotcal.errors import InputError
from rotcal.ingest.formats import REGISTRY, format_of
from rotcal.model.physics import AXES
from rotcal.tables import atomic_write as tables_atomic_write

PARQUET = ".parquet"
IMU_TOPIC = "/imu/calibrated"


@dataclass(frozen=True, eq=False)
class Calibrated:
    """A calibrated recording: stamps (int64 ns), a (3 x n, m/s^2), the
    covariance elements of ``correct.COVARIANCE_PAIRS`` (6 x n) when asked
    for, and what the file records about where they come from."""

    t_ns: np.ndarray
    a: np.ndarray
    cov: np.ndarray | None
    metadata: dict[str, str]

    @property
    def frame(self) -> str:
        return self.metadata["frame"]


def output_format(path: Path) -> str:
    """The form of ``path`` by its suffix (Parquet, or a capture format of
    ``ingest.formats`` that ``WRITERS`` writes); anything else is an input error."""
    suffix = path.suffix.lower()
    form = "parquet" if suffix == PARQUET else getattr(format_of(path), "name", None)
    if form not in WRITERS:
        suffixes = [PARQUET, *(f.suffix for f in REGISTRY if f.name in WRITERS)]
        raise InputError(f"cannot tell the output format from the suffix {suffix or '(none)'!r}: "
                         f"use {', '.join(suffixes)}", path=path)
    return form


def _columns(rec: Calibrated) -> dict[str, np.ndarray]:
    cols = {f"a_{axis}": rec.a[k] for k, axis in enumerate(AXES)}
    if rec.cov is not None:
        u = standard_uncertainty(rec.cov)
        cols |= {f"u_a_{axis}": u[k] for k, axis in enumerate(AXES)}
    return cols


def _write_parquet(rec: Calibrated, fh: BinaryIO) -> None:
    # t in seconds as the CSV inputs have it, t_ns exact
    table = pa.table({"t": rec.t_ns / 1e9, "t_ns": rec.t_ns, **_columns(rec)})
    meta = {f"rotcal.{k}".encode(): v.encode() for k, v in rec.metadata.items()}
    pq.write_table(table.replace_schema_metadata(meta), fh, compression="zstd")


def _write_csv(rec: Calibrated, fh: BinaryIO) -> None:
    # the stamp in decimal seconds exactly (a float64 of an epoch time would round it to ~0.2 us)
    sec, ns = np.divmod(np.abs(rec.t_ns), 1_000_000_000)
    cols = _columns(rec)
    frame = pl.DataFrame({"negative": rec.t_ns < 0, "sec": sec, "ns": ns, **cols}).select(
        pl.format("{}{}.{}", pl.when("negative").then(pl.lit("-")).otherwise(pl.lit("")), "sec",
                  pl.col("ns").cast(pl.String).str.zfill(9)).alias("t"), *cols)
    fh.write("".join(f"# {k}: {v}\n" for k, v in rec.metadata.items()).encode())
    frame.write_csv(fh, float_precision=None)


def _write_mcap(rec: Calibrated, fh: BinaryIO) -> None:
    from rotcal.ingest.formats.mcap.writer import ROS2_LIBRARY, ChunkedWriter, add_imu_messages, register_imu_schema

    writer = ChunkedWriter(fh, "ros2", ROS2_LIBRARY)
    schema = register_imu_schema(writer)
    cov = () if rec.cov is None else list(full_covariance(rec.cov))
    add_imu_messages(writer, schema, IMU_TOPIC, rec.frame, rec.t_ns, list(rec.a), cov)
    writer.finish()


WRITERS: dict[str, Callable[[Calibrated, BinaryIO], None]] = {
    "parquet": _write_parquet, "csv": _write_csv, "mcap": _write_mcap}


def atomic_write(path: Path, write: Callable[[BinaryIO], object], what: str) -> Path:
    """``write`` the file through ``tables.atomic_write``; an error writing
    it is the user's (a full disk, a folder gone): one line naming it."""
    def to_file(tmp: Path) -> None:
        with tmp.open("wb") as fh:
            write(fh)

    try:
        return tables_atomic_write(path, to_file)
    except OSError as exc:
        raise InputError(f"cannot write {what}: {exc.strerror or exc}", path=path) from None


def write_calibrated(rec: Calibrated, path: Path) -> Path:
    """Write ``rec`` to ``path`` in the form its suffix names, atomically."""
    write = WRITERS[output_format(path)]
    return atomic_write(path, lambda fh: write(rec, fh), "the calibrated recording")


def file_metadata(dataset: str, calibration: str, rate_hz: float, frame: str, model: str,
                  uncertainty: bool) -> dict[str, str]:
    """What a calibrated file says about itself."""
    return {"frame": frame, "unit": "m/s^2", "correction": "a = P (R - O)", "calibration": calibration,
            "calibration_rate_hz": repr(rate_hz), "calibration_model": model, "recording": dataset,
            "uncertainty": ("standard uncertainty of the calibration's correction (calibration covariance "
                            "propagated; the sample's own noise excluded)") if uncertainty else "none",
            "rotcal_version": __version__}
