"""``rotcal export``: a calibration in the forms other tools load
(docs/apply.md gives each form's convention and its source).

- ArduPilot (``AP_InertialSensor``): per axis a = INS_ACCSCAL * (raw -
  INS_ACCOFFS), raw and offsets in m/s^2, in the sensor's axes before the
  board rotation (``_rotate_and_correct_accel`` in
  libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp).
- PX4 (``sensor_calibration::Accelerometer::Correct``): per axis a =
  (raw - CAL_ACC0_xOFF) * CAL_ACC0_xSCALE, m/s^2, then the rotation
  CAL_ACC0_ROT (src/lib/sensor_calibration/Accelerometer.hpp).
- YAML in imu_tk's convention (``CalibratedTriad``, include/imu_tk/calibration.h):
  X' = T K (X - B), T a misalignment matrix with unit diagonal, K the
  diagonal scale, B the bias in raw units.
- JSON: a = P (R - O) itself with the uncertainties.

The flight stacks hold a scale and an offset per axis of a driver output
already in m/s^2 (raw = c R with the driver's nominal scale c). Their
per-axis model takes each channel's own sensitivity, so that a_r = (R_r -
O_r) / s_r whatever the calibration's frame: scale_r = 1 / (c s_r), offset_r =
c O_r. What they cannot hold is the non-orthogonality of the axes.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rotcal import __version__
from rotcal.apply.files import atomic_write
from rotcal.errors import InputError
from rotcal.jsontext import json_text
from rotcal.model.calibration import Calibration, RateCalibration

FORMATS = ("ardupilot", "px4", "yaml", "json")
SUFFIXES = {"ardupilot": ".param", "px4": ".params", "yaml": ".yaml", "json": ".json"}
M_S2 = ("m/s^2", "m/s2", "m s^-2", "m/s**2")
# ArduPilot's documented parameter ranges (AP_InertialSensor.cpp @Range)
ARDUPILOT_SCALE_RANGE = (0.8, 1.2)
ARDUPILOT_OFFSET_LIMIT = 3.5
QGC_REAL32 = 9  # MAV_PARAM_TYPE_REAL32, the type column of a QGroundControl parameter file


@dataclass(frozen=True)
class Export:
    """An exported calibration: the file's text and what it could not hold."""

    format: str
    text: str
    warnings: tuple[str, ...]

    def write(self, path: Path) -> Path:
        """The text written to ``path``, atomically."""
        return atomic_write(path, lambda fh: fh.write(self.text.encode()), "the export")


def _float32(x: float) -> str:
    """Nine significant digits: a float32 (the stacks' parameter type) round trips."""
    return f"{x:.9g}"


def _parameters(rc: RateCalibration) -> dict[str, float]:
    return {q.name: q.value for q in rc.parameters}


def per_axis(rc: RateCalibration, nominal_scale: float) -> tuple[np.ndarray, np.ndarray]:
    """The flight stacks' (scale, offset in m/s^2) per axis u, v, w for a
    driver output c R (c = ``nominal_scale``, m/s^2 per output unit)."""
    p = _parameters(rc)
    s = np.array([p["s_u"], p["s_v"], p["s_w"]])
    return 1.0 / (nominal_scale * s), nominal_scale * rc.O_vector


def non_orthogonality_mg(rc: RateCalibration) -> float:
    """The largest error, in mg at 1 g, of a per-axis model in the
    orthogonal axes closest to the sensing axes: with N the responsivity
    vectors' unit directions (rows of Q normalised) and U its polar factor
    (the nearest rotation), a per-axis model reads N a where the truth is
    U a, so the worst case over |a| = 1 g is the largest singular value of N - U."""
    Q = np.linalg.inv(rc.P_matrix)
    N = Q / np.linalg.norm(Q, axis=1, keepdims=True)
    w, _, vt = np.linalg.svd(N)
    return 1000.0 * float(np.linalg.svd(N - w @ vt, compute_uv=False)[0])


def _nominal_scale(cal: Calibration, nominal_scale: float | None, fmt: str) -> float:
    if nominal_scale is not None:
        if not (math.isfinite(nominal_scale) and nominal_scale > 0):
            raise InputError(f"--nominal-scale must be a positive number of m/s^2 per {cal.output_unit}, "
                             f"not {nominal_scale}")
        return nominal_scale
    if cal.output_unit.strip().lower() in M_S2:
        return 1.0
    raise InputError(f"{fmt} takes the driver's output in m/s^2 but the calibration's output unit is "
                     f"{cal.output_unit!r}: give the driver's conversion with --nominal-scale (m/s^2 per "
                     f"{cal.output_unit})")


def _stack_warnings(stack: str, rc: RateCalibration, scale: np.ndarray, offset: np.ndarray) -> list[str]:
    p = _parameters(rc)
    angles = ", ".join(f"{n} - 90 deg = {1000 * (p[n] - 90):+.3g} mdeg" for n in ("phi_uv", "phi_vw", "phi_wu"))
    warnings = [f"{stack} holds a scale and an offset per axis: the non-orthogonality of the axes ({angles}; up to "
                f"{non_orthogonality_mg(rc):.3g} mg at 1 g in the best-aligned orthogonal axes) and the "
                f"uncertainties are not exported"]
    lo, hi = ARDUPILOT_SCALE_RANGE
    if stack == "ArduPilot" and (np.any((scale < lo) | (scale > hi)) or np.any(np.abs(offset) > ARDUPILOT_OFFSET_LIMIT)):
        warnings.append(f"values outside ArduPilot's ranges (INS_ACCSCAL {lo} to {hi}, INS_ACCOFFS within "
                        f"+-{ARDUPILOT_OFFSET_LIMIT} m/s^2): check --nominal-scale against the driver")
    return warnings


def _header(cal: Calibration, rc: RateCalibration, what: str) -> list[str]:
    return [f"rotcal {__version__} export of the calibration of {cal.dataset} ({what})",
            f"rate {rc.rate_hz:g} Hz, model {rc.model}: {rc.reason}"]


def _flight_stack(cal: Calibration, rc: RateCalibration, c: float, stack: str) -> tuple[list[str], list[str], np.ndarray, np.ndarray]:
    scale, offset = per_axis(rc, c)
    notes = [*_header(cal, rc, stack),
             f"per axis a = scale * (raw - offset) in m/s^2, raw = {c!r} m/s^2 per {cal.output_unit} x output;",
             "axes X, Y, Z are the channels u, v, w (the sensor's axes, before the board rotation)"]
    return notes, _stack_warnings(stack, rc, scale, offset), scale, offset


def _ardupilot(cal: Calibration, rc: RateCalibration, c: float) -> Export:
    notes, warnings, scale, offset = _flight_stack(cal, rc, c, "ArduPilot")
    lines = [f"# {n}" for n in notes]
    lines += [f"INS_ACCOFFS_{x},{_float32(v)}" for x, v in zip("XYZ", offset)]
    lines += [f"INS_ACCSCAL_{x},{_float32(v)}" for x, v in zip("XYZ", scale)]
    return Export("ardupilot", "\n".join(lines) + "\n", tuple(warnings))


def _px4(cal: Calibration, rc: RateCalibration, c: float) -> Export:
    notes, warnings, scale, offset = _flight_stack(cal, rc, c, "PX4")
    notes.append("PX4 applies CAL_ACC0_* to the sensor whose device id is CAL_ACC0_ID, which this file does not set: "
                 "keep the vehicle's own CAL_ACC0_ID, and check that it names the calibrated sensor")
    lines = ["# Onboard parameters for Vehicle 1", "#", "# Stack: PX4 Pro", *(f"# {n}" for n in notes), "#",
             "# Vehicle-Id Component-Id Name Value Type"]
    values = [*(("OFF", x, v) for x, v in zip("XYZ", offset)), *(("SCALE", x, v) for x, v in zip("XYZ", scale))]
    lines += [f"1\t1\tCAL_ACC0_{x}{kind}\t{_float32(v)}\t{QGC_REAL32}" for kind, x, v in values]
    return Export("px4", "\n".join(lines) + "\n", tuple(warnings))


def _yaml_float(x: float) -> str:
    # YAML 1.1 readers (PyYAML) need a point in a float's mantissa: 1e-05 would read as a string
    text = repr(float(x))
    return text.replace("e", ".0e") if "e" in text and "." not in text else text


def _yaml_matrix(m: np.ndarray) -> str:
    return "[" + ", ".join("[" + ", ".join(_yaml_float(v) for v in row) + "]" for row in m) + "]"


def imu_tk_matrices(rc: RateCalibration) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """imu_tk's T (unit diagonal), K (diagonal) and B with T K = P, B = O exactly."""
    P = rc.P_matrix
    K = np.diag(np.diag(P))
    return P / np.diag(P)[None, :], K, rc.O_vector


def _yaml(cal: Calibration, rc: RateCalibration) -> Export:
    T, K, B = imu_tk_matrices(rc)
    # imu_tk's names: T = [[1, -mis_yz, mis_zy], [mis_xz, 1, -mis_zx], [-mis_xy, mis_yx, 1]]
    mis = {"mis_yz": -T[0, 1], "mis_zy": T[0, 2], "mis_zx": -T[1, 2], "mis_xz": T[1, 0], "mis_xy": -T[2, 0],
           "mis_yx": T[2, 1]}
    lines = [*(f"# {n}" for n in _header(cal, rc, "imu_tk's CalibratedTriad convention")),
             f"# X' = T K (X - B): X the raw output ({cal.output_unit}), X' in m/s^2 in the frame below",
             'model: "X\' = T K (X - B)"', 'convention: "imu_tk CalibratedTriad"',
             f"dataset: {json.dumps(cal.dataset)}", f"rate_hz: {_yaml_float(rc.rate_hz)}",
             f"frame: {json.dumps(rc.frame)}", f"raw_unit: {json.dumps(cal.output_unit)}", 'calibrated_unit: "m/s^2"',
             f"T: {_yaml_matrix(T)}", f"K: {_yaml_matrix(K)}", f"B: [{', '.join(_yaml_float(v) for v in B)}]",
             "misalignment: {" + ", ".join(f"{k}: {_yaml_float(v)}" for k, v in mis.items()) + "}",
             "scale: {" + ", ".join(f"s_{x}: {_yaml_float(K[i, i])}" for i, x in enumerate("xyz")) + "}"]
    return Export("yaml", "\n".join(lines) + "\n",
                  ("the YAML holds no uncertainties (the JSON export and calibration.json do)",))


def _json(cal: Calibration, rc: RateCalibration) -> Export:
    doc = {"model": "a = P (R - O)", "source": f"rotcal {__version__}", "dataset": cal.dataset, "rate_hz": rc.rate_hz,
           "calibration_model": rc.model, "frame": rc.frame, "output_unit": cal.output_unit,
           "acceleration_unit": "m/s^2", "g_local": cal.g_local,
           "P": rc.P_matrix.tolist(), "O": rc.O_vector.tolist(),
           "u_P": np.array([q.std_uncertainty for q in rc.P]).reshape(3, 3).tolist(),
           "u_O": [q.std_uncertainty for q in rc.O],
           "covariance": {"of": "P row-major, then O", "matrix": rc.correction_cov.tolist()}}
    return Export("json", json_text(doc), ())


def export_calibration(cal: Calibration, fmt: str, rate_hz: float | None = None,
                       nominal_scale: float | None = None) -> Export:
    """``cal``'s entry for ``rate_hz`` (None: DC) in the form ``fmt``, with
    warnings naming what the form cannot hold. ``nominal_scale`` (m/s^2 per
    output unit) is the driver's conversion the flight stacks' raw data has
    been through; required for them unless the output unit is m/s^2."""
    if fmt not in FORMATS:
        raise InputError(f"unknown export format {fmt!r}: use one of {', '.join(FORMATS)}")
    rc = cal.rate(rate_hz)
    if fmt == "ardupilot":
        return _ardupilot(cal, rc, _nominal_scale(cal, nominal_scale, "ArduPilot"))
    if fmt == "px4":
        return _px4(cal, rc, _nominal_scale(cal, nominal_scale, "PX4"))
    return _yaml(cal, rc) if fmt == "yaml" else _json(cal, rc)
