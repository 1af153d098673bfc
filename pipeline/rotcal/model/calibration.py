"""The calibration a run hands over (``calibration.json``): per rate, the
recommended model's nine intrinsic parameters and the correction
a = P (R - O) (Geist 2017 Eq. 18), every quantity with its standard
uncertainty, effective degrees of freedom, coverage factor and expanded
uncertainty (GUM 6.2, G.4), and the joint covariance that ``rotcal apply``
propagates to each corrected sample (GUM 5.1.2).

One home for the document: ``rate_calibration`` builds a rate's entry from
an ``IntrinsicResult``, ``Calibration.to_json`` writes the whole document
(validated against ``schemas/calibration.json``) and ``Calibration.read``
reads it back, for ``rotcal apply``, ``rotcal export`` and the certificate.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from functools import cache, lru_cache
from pathlib import Path
from typing import Any, Protocol

import jsonschema
import numpy as np
import polars as pl

from rotcal.errors import InputError
from rotcal.jsontext import json_text
from rotcal.model.identification import Identification
from rotcal.model.physics import AXES, CHANNELS, INTRINSIC
from rotcal.model.results import EXPANDED_COVERAGE, IntrinsicResult, coverage_factor
from rotcal_schemas import schema_text

CALIBRATION_SCHEMA = "calibration"
CALIBRATION_VERSION = "1.1"  # 1.1: certificate (the laboratory's, customer's, item's, equipment's fields)
BASELINE, REFINED = "baseline", "refined"


def recommended_model(intrinsic: pl.DataFrame, modelled: tuple[str, ...], baseline_reason: str,
                      static_choice: tuple[str, str] | None = None) -> tuple[str, str]:
    """The model of ``intrinsic.parquet`` whose rows are the result, and why.

    The refined model where the diagnosis modelled effects (``modelled``,
    its findings): the papers' model omits them, so its estimates carry
    their bias (a channel delay's phase read as angle; Geist 2017's model
    has no term for it), while the refined one estimates the same nine
    parameters with the effects as extra terms. For static poses of unknown
    orientation, the nested model the evidence chooses (``static_choice``:
    its name and the F test's verdict, ``combine.posemodels``). The baseline
    otherwise, for ``baseline_reason`` (no effect found, or the diagnosis
    not run). The one place that chooses."""
    models = set(intrinsic["model"].to_list())
    if REFINED in models and modelled:
        held = f"; {baseline_reason}" if baseline_reason.startswith("left out") else ""  # the held-out figures, where compared
        return REFINED, f"the diagnosis modelled {', '.join(modelled)}; the baseline model omits {'it' if len(modelled) == 1 else 'them'}{held}"
    if static_choice is not None and static_choice[0] in models:
        return static_choice
    return BASELINE, baseline_reason


@dataclass(frozen=True, eq=False)
class Recommended:
    """The recommended model, why, and its results per rate with the frames
    of their responsivity vectors."""

    model: str
    reason: str
    results: tuple[IntrinsicResult, ...]
    frames: tuple[str, ...]


def recommend(intrinsic: pl.DataFrame, results: tuple[IntrinsicResult, ...], frames: tuple[str, ...],
              others: dict[str, tuple[IntrinsicResult, ...]], modelled: tuple[str, ...], baseline_reason: str,
              static_choice: tuple[str, str] | None = None) -> Recommended:
    """The recommended model (``recommended_model``) with its results, in
    the frames of ``results`` (the first model's): those ``results``, or
    the ``others`` of its name (refined, a static recording's nested models)."""
    model, reason = recommended_model(intrinsic, modelled, baseline_reason, static_choice)
    if model not in others:
        return Recommended(model, reason, results, frames)
    frame_of = dict(zip((r.rate_hz for r in results), frames))
    return Recommended(model, reason, others[model], tuple(frame_of[r.rate_hz] for r in others[model]))


def mark_recommended(intrinsic: pl.DataFrame, model: str) -> pl.DataFrame:
    """``intrinsic`` with its ``recommended`` column: the rows of ``model``."""
    return intrinsic.with_columns(recommended=pl.col("model") == model)


def created_utc() -> str:
    """The time of the run, UTC ISO 8601 to the second; ``SOURCE_DATE_EPOCH``
    (reproducible-builds.org) when set, so that reruns are bit-identical."""
    epoch = os.environ.get("SOURCE_DATE_EPOCH")
    when = datetime.fromtimestamp(int(epoch), UTC) if epoch and epoch.isdigit() else datetime.now(UTC)
    return when.isoformat(timespec="seconds").replace("+00:00", "Z")


@dataclass(frozen=True)
class Quantity:
    """One calibrated quantity: value, standard uncertainty u, effective
    degrees of freedom (inf: Type B inputs only), k = t_0.975(dof) and U = k u."""

    name: str
    value: float
    std_uncertainty: float
    dof: float
    unit: str

    @property
    def coverage_factor(self) -> float:
        return _coverage_factor(self.dof)

    @property
    def expanded_uncertainty(self) -> float:
        return self.coverage_factor * self.std_uncertainty

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "std_uncertainty": self.std_uncertainty,
                "dof": None if math.isinf(self.dof) else self.dof, "coverage_factor": self.coverage_factor,
                "expanded_uncertainty": self.expanded_uncertainty, "coverage_probability": EXPANDED_COVERAGE,
                "unit": self.unit}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Quantity:
        return cls(d["name"], float(d["value"]), float(d["std_uncertainty"]),
                   math.inf if d["dof"] is None else float(d["dof"]), d["unit"])


@lru_cache(maxsize=4096)
def _coverage_factor(dof: float) -> float:
    """k = t_0.975(dof) of one quantity, each dof computed once a process:
    a document's quantities ask for it twice and the certificate again
    (about 400 t quantiles a dataset otherwise)."""
    return float(coverage_factor(np.array([dof]))[0])


def _quantities(names: list[str], values: np.ndarray, u: np.ndarray, dof: np.ndarray, units: list[str]) -> tuple[Quantity, ...]:
    return tuple(Quantity(n, float(v), float(s), float(d), un) for n, v, s, d, un in zip(names, values, u, dof, units))


def matrix_names(matrix: str) -> list[str]:
    """Row-major element names: P_xu, P_xv, ... (rows x, y, z; columns u, v, w) or Q_ux, ..."""
    rows, cols = (AXES, CHANNELS) if matrix == "P" else (CHANNELS, AXES)
    return [f"{matrix}_{r}{c}" for r in rows for c in cols]


@dataclass(frozen=True)
class RateCalibration:
    """The calibration of one rate (0: DC, the static result): the model it
    comes from and why that one is recommended, the frame of P's rows, the
    nine intrinsic parameters with their 9 x 9 covariance, and P (3 x 3,
    m/s^2 per output unit) and O (output units) with the 12 x 12 covariance
    of (P row-major, O), g_local's uncertainty included."""

    rate_hz: float
    model: str
    reason: str
    frame: str
    parameters: tuple[Quantity, ...]
    parameter_cov: np.ndarray
    P: tuple[Quantity, ...]
    Q: tuple[Quantity, ...]
    O: tuple[Quantity, ...]  # noqa: E741 (the papers name the offsets O)
    correction_cov: np.ndarray

    @property
    def P_matrix(self) -> np.ndarray:
        return np.array([q.value for q in self.P]).reshape(3, 3)

    @property
    def O_vector(self) -> np.ndarray:
        return np.array([q.value for q in self.O])

    def parameter(self, name: str) -> Quantity:
        """The intrinsic parameter ``name`` (s_u, ..., phi_uv, ..., O_u, ...)."""
        for q in self.parameters:
            if q.name == name:
                return q
        raise KeyError(f"no parameter {name!r}: {', '.join(q.name for q in self.parameters)}")

    def to_dict(self) -> dict[str, Any]:
        return {"rate_hz": self.rate_hz, "model": self.model, "reason": self.reason, "frame": self.frame,
                "parameters": [q.to_dict() for q in self.parameters],
                "parameter_covariance": self.parameter_cov.tolist(),
                "P": [q.to_dict() for q in self.P], "Q": [q.to_dict() for q in self.Q],
                "O": [q.to_dict() for q in self.O], "correction_covariance": self.correction_cov.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> RateCalibration:
        def qs(key: str) -> tuple[Quantity, ...]:
            return tuple(Quantity.from_dict(q) for q in d[key])

        return cls(float(d["rate_hz"]), d["model"], d["reason"], d["frame"], qs("parameters"),
                   np.array(d["parameter_covariance"], float), qs("P"), qs("Q"), qs("O"),
                   np.array(d["correction_covariance"], float))


def rate_calibration(result: IntrinsicResult, frame: str, model: str, reason: str, unit: str) -> RateCalibration:
    """A rate's entry from its intrinsic result: the parameters as
    ``intrinsic.parquet`` has them, and P = Q^-1, Q = state / g (Geist 2017
    Eqs. 18 to 22) with O, their covariance carried to first order through
    the Jacobian of (Q, g) -> (P, O) (dP = -P dQ P; dP/dg = P / g), and each
    element's effective dof from the result's input groups (GUM G.4.1)."""
    g = result.g_local
    Q = result.state[:9].reshape(3, 3) / g
    P = np.linalg.inv(Q)
    jac = np.zeros((12, 12))
    jac[:9, :9] = -np.einsum("ik,lj->ijkl", P, P).reshape(9, 9) / g
    jac[9:, 9:] = np.eye(3)
    jac_g = np.concatenate([P.ravel() / g, np.zeros(3)])
    corr_cov = jac @ result.state_cov @ jac.T + np.outer(jac_g, jac_g) * result.g_uncertainty**2
    corr_dof = result.welch_satterthwaite(jac, jac_g)
    jac_q = np.zeros((9, 12))
    jac_q[:, :9] = np.eye(9) / g
    jac_qg = -Q.ravel() / g
    q_cov = jac_q @ result.state_cov @ jac_q.T + np.outer(jac_qg, jac_qg) * result.g_uncertainty**2
    p_unit, q_unit = f"(m/s^2)/{unit}", f"{unit}/(m/s^2)"
    param_units = [f"{unit}/(m/s^2)"] * 3 + ["deg"] * 3 + [unit] * 3
    corr_u = np.sqrt(np.diag(corr_cov))
    return RateCalibration(
        result.rate_hz, model, reason, frame,
        _quantities(list(INTRINSIC), result.value, result.std_uncertainty, result.dof, param_units), result.cov,
        _quantities(matrix_names("P"), P.ravel(), corr_u[:9], corr_dof[:9], [p_unit] * 9),
        _quantities(matrix_names("Q"), Q.ravel(), np.sqrt(np.diag(q_cov)), result.welch_satterthwaite(jac_q, jac_qg),
                    [q_unit] * 9),
        _quantities([f"O_{c}" for c in CHANNELS], result.state[9:], corr_u[9:],
                    corr_dof[9:], [unit] * 3),
        corr_cov)


@cache
def _validator() -> jsonschema.Draft202012Validator:
    """The validator of ``schemas/calibration.json`` that reads a document
    and names what is wrong with it, built once a process."""
    return jsonschema.Draft202012Validator(schema_text(CALIBRATION_SCHEMA))


@cache
def _compiled_validator() -> Callable[[dict], object]:
    """``schemas/calibration.json`` compiled to Python code once a process
    (fastjsonschema): the check of every document a run writes, about 1 ms
    where jsonschema's walk of its 3,300 nodes took 18 ms. It raises
    ``fastjsonschema.JsonSchemaException`` on a document the schema refuses."""
    import fastjsonschema

    return fastjsonschema.compile(schema_text(CALIBRATION_SCHEMA))


@dataclass(frozen=True)
class Calibration:
    """``calibration.json``: the dataset, the DUT's output unit, g_local with
    its standard uncertainty and source, the inputs' content hashes, the run's
    configuration, rotcal's version and the time of the run, and the
    recommended calibration per rate; what the certificate states beside the
    results, as the laboratory gave it (``identification``)."""

    dataset: str
    device: dict[str, Any]
    output_unit: str
    g_local: float
    g_local_uncertainty: float
    g_local_source: str
    inputs: tuple[dict[str, Any], ...]
    configuration: dict[str, Any]
    rotcal_version: str
    created_utc: str
    rates: tuple[RateCalibration, ...]
    identification: Identification = Identification()

    def rate(self, rate_hz: float | None) -> RateCalibration:
        """The entry of ``rate_hz`` (None: DC when there is one, else the only rate)."""
        if rate_hz is None:
            dc = [r for r in self.rates if r.rate_hz == 0.0]
            if dc or len(self.rates) == 1:
                return (dc or list(self.rates))[0]
            raise InputError(f"calibration of {self.dataset} has rates {[r.rate_hz for r in self.rates]} Hz and no DC "
                             f"result: choose one with --rate")
        for r in self.rates:
            if math.isclose(r.rate_hz, rate_hz, rel_tol=1e-9, abs_tol=1e-12):
                return r
        raise InputError(f"calibration of {self.dataset} has no rate {rate_hz:g} Hz "
                         f"(it has {', '.join(f'{r.rate_hz:g}' for r in self.rates)})")

    def to_dict(self) -> dict[str, Any]:
        return {"schema": CALIBRATION_SCHEMA, "version": CALIBRATION_VERSION, "dataset": self.dataset,
                "device": self.device, "output_unit": self.output_unit,
                "g_local": {"value": self.g_local, "std_uncertainty": self.g_local_uncertainty,
                            "source": self.g_local_source},
                "coverage_probability": EXPANDED_COVERAGE, "inputs": list(self.inputs),
                "configuration": self.configuration, "rotcal_version": self.rotcal_version,
                "created_utc": self.created_utc, "rates": [r.to_dict() for r in self.rates],
                "certificate": self.identification.to_dict()}

    def write(self, path: Path) -> Path:
        """Write the document (validated first: a bug, not the user's input, if it fails)."""
        doc = self.to_dict()
        _compiled_validator()(doc)
        path.write_text(json_text(doc))
        return path

    @classmethod
    def read(cls, path: Path) -> Calibration:
        """Read ``calibration.json`` (or a run's output directory holding
        one); a file that is not a valid calibration document is an input error."""
        path = Path(path)
        if path.is_dir():
            path = path / "calibration.json"
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise InputError(f"cannot read calibration: {exc}", path=path) from None
        errors = sorted(_validator().iter_errors(doc),
                        key=lambda e: list(e.absolute_path))
        if errors:
            where = "/".join(str(p) for p in errors[0].absolute_path) or "document"
            raise InputError(f"not a rotcal calibration: {where}: {errors[0].message}", path=path)
        return cls.from_dict(doc)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Calibration:
        """The calibration of a document already valid against ``schemas/calibration.json``."""
        g = doc["g_local"]
        return cls(doc["dataset"], doc["device"], doc["output_unit"], float(g["value"]), float(g["std_uncertainty"]),
                   g["source"], tuple(doc["inputs"]), doc["configuration"], doc["rotcal_version"], doc["created_utc"],
                   tuple(RateCalibration.from_dict(r) for r in doc["rates"]),
                   Identification.from_dict(doc.get("certificate", {})))


class DeviceMeta(Protocol):
    """What the document records of a dataset's metadata (``dataset.toml``,
    read by ``rotcal.ingest.meta``): the device, the local gravity and the certificate's fields."""

    @property
    def device_id(self) -> str | None: ...
    @property
    def output_unit(self) -> str: ...
    @property
    def full_scale(self) -> float | None: ...
    @property
    def g_local(self) -> float: ...
    @property
    def g_local_uncertainty(self) -> float: ...
    @property
    def g_local_source(self) -> str: ...
    @property
    def identification(self) -> Identification: ...


def recommended_calibration(chosen: Recommended, dataset: str, meta: DeviceMeta, inputs: tuple[dict[str, Any], ...],
                            configuration: dict[str, Any], site: Identification = Identification()) -> Calibration:
    """The run's document: ``chosen``'s result per rate, the dataset's
    metadata (device, g_local and its source; the certificate's fields,
    each absent one from the ``site`` file's), rotcal's version and the
    time of the run (``created_utc``)."""
    from rotcal import __version__

    unit = meta.output_unit
    device = {k: v for k, v in (("id", meta.device_id), ("output_unit", unit), ("full_scale", meta.full_scale))
              if v is not None}
    return Calibration(dataset, device, unit, meta.g_local, meta.g_local_uncertainty, meta.g_local_source, inputs,
                       configuration, __version__, created_utc(),
                       tuple(rate_calibration(r, f, chosen.model, chosen.reason, unit)
                             for r, f in zip(chosen.results, chosen.frames)),
                       meta.identification.over(site))
