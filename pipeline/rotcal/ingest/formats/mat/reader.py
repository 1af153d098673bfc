"""MATLAB captures (docs/inputs.md, "MATLAB captures"), read with
``scipy.io.loadmat``: the files MATLAB's ``save`` writes by default
(versions 4 to 7.2; a version 7.3 file is HDF5 and refused with what to do).

The variables read, by name (any other variable is ignored):

- the outputs: ``u``, ``v``, ``w`` (N values each), or else the one
  numeric matrix of N x 3 (u, v, w) or N x 4 (t, u, v, w) values, either
  way round;
- the time in seconds: ``t`` or ``time`` (N values), the matrix's first
  column, or else ``[format] sample_rate_hz`` of dataset.toml;
- labels, optional: ``axis`` (characters x, y, z: one for the whole capture
  or one a sample), ``rate_hz`` or ``rate`` (Hz), ``angle_deg`` or
  ``angle`` (degrees), ``temperature_c``.

They become the columns of a CSV capture and go through the same checks
(``ingest.labels.label_columns``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import polars as pl
import scipy.io

from rotcal.config import Limits
from rotcal.errors import InputError
from rotcal.ingest.files import open_capture
from rotcal.ingest.labels import label_columns
from rotcal.ingest.meta import CaptureSpec, DatasetMeta

OUTPUTS = ("u", "v", "w")
TIME = ("t", "time")
NUMBERS = {"rate_hz": ("rate_hz", "rate"), "angle_deg": ("angle_deg", "angle"), "temperature_c": ("temperature_c",)}
NUMERIC = {"double", "single", "int8", "int16", "int32", "int64", "uint8", "uint16", "uint32", "uint64"}


def _variables(fh: Any, path: Path) -> dict[str, tuple[tuple[int, ...], str]]:
    """Each variable's shape and MATLAB class, from the file's headers (``whosmat``: no data read)."""
    try:
        return {name: (tuple(shape), kind) for name, shape, kind in scipy.io.whosmat(fh)}
    except NotImplementedError:
        raise InputError("a MATLAB v7.3 file (HDF5): save it as version 7 (save(file, '-v7')) or as CSV",
                         path=path) from None
    except Exception as exc:  # scipy raises ValueError, TypeError or OSError for what is not a MAT file
        raise InputError(f"cannot be read as a MATLAB file: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
                         path=path) from None


def _matrix(found: dict[str, tuple[tuple[int, ...], str]], path: Path) -> str:
    """The one numeric N x 3 or N x 4 matrix (or its transpose) of a file without ``u, v, w``."""
    matrices = [name for name, (shape, kind) in found.items() if kind in NUMERIC and len(shape) == 2
                and max(shape) > 4 and min(shape) in (3, 4)]
    if len(matrices) == 1:
        return matrices[0]
    listing = ", ".join(f"{n} ({' x '.join(map(str, s))} {k})" for n, (s, k) in found.items()) or "none"
    what = "several matrices of 3 or 4 columns" if matrices else "no variables u, v, w nor a matrix of 3 or 4 columns"
    raise InputError(f"{what} (variables: {listing})", path=path,
                     hint="name the outputs u, v, w (docs/inputs.md, \"MATLAB captures\")")


def _vector(values: np.ndarray, name: str, n: int, path: Path) -> np.ndarray:
    """A variable's N numbers (a row or a column), as float64."""
    flat = np.asarray(values).ravel()
    if flat.size != n:
        raise InputError(f"variable {name!r} holds {flat.size} values where the outputs have {n}", path=path)
    if flat.dtype.kind not in "fiub":
        raise InputError(f"variable {name!r} is not numeric ({flat.dtype})", path=path)
    return flat.astype(np.float64)


def _axis(values: np.ndarray, n: int, path: Path) -> list[str | None]:
    """Axis labels: a character array (one character a sample, or one for
    every sample), or a cell array of strings."""
    flat = np.asarray(values).ravel()
    if flat.dtype.kind == "O":
        labels = [str(np.asarray(v).ravel()[0]) if np.asarray(v).size else "" for v in flat]
    elif flat.dtype.kind == "U":
        text = "".join(flat.tolist())
        labels = list(text) if len(text) != 1 else [text] * n
    else:
        raise InputError(f"variable 'axis' is not text ({flat.dtype})", path=path)
    if len(labels) != n:
        raise InputError(f"variable 'axis' holds {len(labels)} labels where the outputs have {n}", path=path)
    return [label.strip() or None for label in labels]


def _columns(path: Path, meta: DatasetMeta) -> dict[str, Any]:
    """The capture's columns by the names of docs/inputs.md (``t`` in seconds)."""
    with open_capture(path) as fh:
        if fh.seek(0, 2) == 0:
            raise InputError("the file is empty", path=path)
        fh.seek(0)
        found = _variables(fh, path)
        matrix = None if all(c in found for c in OUTPUTS) else _matrix(found, path)
        time = next((t for t in TIME if t in found), None)
        labels = [v for names in NUMBERS.values() for v in names if v in found] + (["axis"] if "axis" in found else [])
        wanted = [*(OUTPUTS if matrix is None else (matrix,)), *([time] if time else []), *labels]
        fh.seek(0)
        try:
            data = scipy.io.loadmat(fh, variable_names=wanted)
        except Exception as exc:  # a file whose headers read but whose data does not
            raise InputError(f"cannot be read as a MATLAB file: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}",
                             path=path) from None
    columns: dict[str, Any] = {}
    if matrix is not None:
        m = np.asarray(data[matrix])
        m = m if m.shape[0] > m.shape[1] else m.T
        if m.shape[1] == 4:
            columns["t"] = m[:, 0].astype(np.float64)
        columns |= {c: m[:, -3 + k].astype(np.float64) for k, c in enumerate(OUTPUTS)}
    n = columns["u"].size if matrix is not None else np.asarray(data["u"]).size
    if matrix is None:
        columns |= {c: _vector(data[c], c, n, path) for c in OUTPUTS}
    if "t" not in columns and time is not None:
        columns["t"] = _vector(data[time], time, n, path)
    if "t" not in columns:
        if meta.csv_format.sample_rate_hz is None:
            raise InputError("no time: a variable t or time (seconds), a matrix of 4 columns, or dataset.toml "
                             "[format] sample_rate_hz", path=path)
        columns["t"] = np.arange(n, dtype=np.float64) / meta.csv_format.sample_rate_hz
    for column, names in NUMBERS.items():
        name = next((v for v in names if v in data), None)
        if name is not None:
            columns[column] = _vector(data[name], name, n, path)
    if "axis" in data:
        columns["axis"] = _axis(data["axis"], n, path)
    return columns


def read_capture(path: Path, spec: CaptureSpec | None, meta: DatasetMeta, limits: Limits,
                 workers: int = 0) -> tuple[pl.DataFrame, tuple[str, ...]]:
    """The registry's reader (``ingest.formats``): one MATLAB capture as
    canonical sample columns, labelled as a CSV capture's are."""
    columns = _columns(path, meta)
    if not columns["u"].size:
        raise InputError("the file has no samples", path=path)
    frame = pl.DataFrame({name: pl.Series(name, values, dtype=pl.String if name == "axis" else pl.Float64)
                          for name, values in columns.items()})
    return label_columns(frame, spec, path), ()
