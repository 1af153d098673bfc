"""Cross-sensitivity matrices (Geist 2017 section 4) and the reverse:
intrinsic parameters from a matrix another laboratory reports (section 6).

Geist's Eq. 18 writes the acceleration from the offset-free output,
a = P (R - O); Eq. 19 the output from the acceleration, R - O = Q a, with
the responsivity vectors as the rows of Q; Eq. 22: Q = P^-1. rotcal's state
holds g Q, so

    Q = state / g,    P = Q^-1,    dP = -P dQ P,

and the covariance of P is the covariance of Q (with g_local's) carried
through the Jacobian of the inverse. (Eq. 20 prints Q with q_xy and q_xz
below the diagonal, as if it were symmetric; Eqs. 21 and 22 have the
general form, which rotcal uses.)

The matrices are in the frame the result was measured in: the table frame
for table segments, the DUT case's frame for labelled poses, and the
intrinsic frame (u along x, v in the x-y plane) for an orientation-free
fit. The intrinsic parameters do not depend on it (Eq. 23).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import polars as pl

from rotcal.errors import InputError
from rotcal.model.physics import AXES, CHANNELS, INTRINSIC
from rotcal.model.results import IntrinsicResult, intrinsic_jacobian
from rotcal.tables import conform, schema, write_parquet

MATRIX_PARAMETERS = INTRINSIC[:6]


@dataclass(frozen=True, eq=False)
class CrossSensitivity:
    """P (m/s^2 per output unit, rows x, y, z, columns u, v, w) and Q = P^-1
    (output unit per m/s^2, rows u, v, w, columns x, y, z), each with the
    9 x 9 covariance of its row-major elements."""

    P: np.ndarray
    cov_P: np.ndarray
    Q: np.ndarray
    cov_Q: np.ndarray


def inverse_jacobian(matrix: np.ndarray) -> np.ndarray:
    """d vec(M^-1) / d vec(M) for row-major vec: -M^-1_ik M^-1_lj."""
    inv = np.linalg.inv(matrix)
    return -np.einsum("ik,lj->ijkl", inv, inv).reshape(9, 9)


def cross_sensitivity(result: IntrinsicResult, g_uncertainty: float) -> CrossSensitivity:
    """P and Q of one result (Geist 2017 Eqs. 18 to 22) with covariances."""
    g = result.g_local
    Q = result.state[:9].reshape(3, 3) / g
    vec_q = Q.ravel()
    cov_Q = result.state_cov[:9, :9] / g**2 + np.outer(vec_q, vec_q) * (g_uncertainty / g) ** 2
    jac = inverse_jacobian(Q)
    return CrossSensitivity(np.linalg.inv(Q), jac @ cov_Q @ jac.T, Q, cov_Q)


def intrinsic_from_matrix(P: np.ndarray, cov_P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The six sensitivity and angle parameters of a cross-sensitivity
    matrix P (Geist 2017 Eq. 23, then Eqs. 14 and 16) and their covariance,
    propagated to first order through the inverse and Eqs. 14 and 16."""
    Q = np.linalg.inv(P)
    jac_q = inverse_jacobian(P)
    value, jac, _ = intrinsic_jacobian(np.concatenate([Q.ravel(), np.zeros(3)]), 1.0)
    total = jac[:6, :9] @ jac_q
    return value[:6], total @ cov_P @ total.T


def matrix_units(output_unit: str) -> dict[str, str]:
    return {"P": f"(m/s^2)/{output_unit}", "Q": f"{output_unit}/(m/s^2)"}


def cross_sensitivity_frame(results: list[tuple[IntrinsicResult, str]], dataset: str, model: str,
                            output_unit: str, g_uncertainty: float) -> pl.DataFrame:
    """The ``cross_sensitivity`` table: P and Q of every (result, frame),
    one row per element with its covariance with the matrix's nine elements."""
    units = matrix_units(output_unit)
    rows = []
    for res, frame in results:
        cs = cross_sensitivity(res, g_uncertainty)
        for name, mat, cov, row_names, col_names in (("P", cs.P, cs.cov_P, AXES, CHANNELS),
                                                     ("Q", cs.Q, cs.cov_Q, CHANNELS, AXES)):
            for k in range(9):
                i, j = divmod(k, 3)
                rows.append({"dataset": dataset, "model": model, "rate_hz": res.rate_hz, "frame": frame,
                             "matrix": name, "row": row_names[i], "column": col_names[j],
                             "value": mat[i, j], "std_uncertainty": float(np.sqrt(cov[k, k])),
                             "unit": units[name], "cov": cov[k].tolist()})
    if not rows:
        return schema("cross_sensitivity").empty()
    return conform(pl.DataFrame(rows, schema_overrides=schema("cross_sensitivity").polars_schema), "cross_sensitivity")


def _numbers(path: Path, line_no: int, cells: list[str]) -> list[float]:
    try:
        if len(cells) in (3, 4):
            return [float(c) for c in cells[-3:]]
    except ValueError:
        pass
    raise InputError(f"line {line_no}: expected three numbers (u, v, w), optionally after a row label x, y or z; "
                     f"found {', '.join(cells)!r}", path=path)


def read_matrix_csv(path: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """A cross-sensitivity matrix file (docs/inputs.md, "rotcal intrinsic --matrix FILE"): rows x, y, z and
    columns u, v, w of P, optionally followed by three rows of standard
    uncertainties. A header row (``,u,v,w``) and a first column of row
    labels are optional; lines starting with ``#`` are comments."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (FileNotFoundError, IsADirectoryError):
        raise InputError("matrix file not found", path=path) from None
    except UnicodeDecodeError:
        raise InputError("matrix file is not UTF-8 text", path=path) from None
    lines = [(k + 1, row) for k, row in enumerate(csv.reader(text.splitlines()))
             if row and any(c.strip() for c in row) and not row[0].lstrip().startswith("#")]
    rows, labels = [], []
    for k, (line_no, row) in enumerate(lines):
        cells = [c.strip() for c in row]
        if k == 0 and [c.lower() for c in cells[-3:]] == list(CHANNELS):
            continue
        rows.append(_numbers(path, line_no, cells))
        labels.append(cells[0].lower() if len(cells) == 4 else None)
    if len(rows) not in (3, 6):
        raise InputError(f"expected 3 rows of P (x, y, z), or 6 with their standard uncertainties; found {len(rows)}",
                         path=path)
    for k, label in enumerate(labels):
        if label is not None and label.removeprefix("u_").removeprefix("u(").rstrip(")") != AXES[k % 3]:
            raise InputError(f"row {k + 1} is labelled {label!r}; rows must be x, y, z in order", path=path)
    values = np.array(rows, float)
    if not np.all(np.isfinite(values)):
        raise InputError("the matrix holds non-finite values", path=path)
    P, u = values[:3], (values[3:] if len(rows) == 6 else None)
    if u is not None and np.any(u < 0):
        raise InputError("standard uncertainties must not be negative", path=path)
    if abs(np.linalg.det(P)) <= 1e-12 * np.prod(np.linalg.norm(P, axis=1)):
        raise InputError("the matrix is singular: it has no inverse, so no responsivity vectors", path=path)
    return P, u


def matrix_intrinsic_frame(source: str, value: np.ndarray, cov: np.ndarray, output_unit: str) -> pl.DataFrame:
    """The ``matrix_intrinsic`` table: the six parameters of a matrix file."""
    units = (f"{output_unit}/(m/s^2)",) * 3 + ("deg",) * 3
    frame = pl.DataFrame({"source": [source] * 6, "parameter": list(MATRIX_PARAMETERS), "value": value,
                          "std_uncertainty": np.sqrt(np.diag(cov)), "unit": list(units)})
    return conform(frame, "matrix_intrinsic")


def matrix_intrinsic(matrix_path: Path, out_dir: Path, output_unit: str) -> tuple[pl.DataFrame, Path]:
    """``rotcal intrinsic --matrix``: read the file, compute the six
    parameters (standard uncertainties taken as independent; NaN when the
    file gives none) and write ``<stem>_intrinsic.parquet`` into ``out_dir``."""
    P, u = read_matrix_csv(matrix_path)
    value, cov = intrinsic_from_matrix(P, np.diag(u.ravel() ** 2) if u is not None else np.zeros((9, 9)))
    if u is None:
        cov = np.full_like(cov, np.nan)
    frame = matrix_intrinsic_frame(Path(matrix_path).name, value, cov, output_unit)
    return frame, write_parquet(frame, Path(out_dir) / f"{Path(matrix_path).stem}_intrinsic.parquet", "matrix_intrinsic")
