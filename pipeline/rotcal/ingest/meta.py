"""``dataset.toml``: read, validate against ``schemas/dataset_toml.json``,
and resolve defaults once into a frozen record (docs/inputs.md)."""

from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from datetime import date, datetime, time
from pathlib import Path

import jsonschema

from rotcal.errors import InputError
from rotcal.model.constants import STANDARD_GRAVITY, STANDARD_GRAVITY_UNCERTAINTY
from rotcal.model.identification import Identification, identification_from_toml
from rotcal.model.placement import Placement
from rotcal_schemas import schema_text

# The deepest valid value is three levels down ([[capture]] -> table -> key);
# far deeper nesting is hostile (400 levels overflow tomllib's recursion).
MAX_NESTING = 8
INT64 = 2**63  # TOML integers are 64-bit (TOML 1.0, "Integer")

DELIMITERS = {",": ",", ";": ";", "\t": "\t", "tab": "\t", "whitespace": "whitespace"}
# the time column's unit: time stamps per second, or ISO 8601 date-times (``None``)
TIME_UNITS: dict[str, float | None] = {"s": 1.0, "ms": 1e3, "us": 1e6, "ns": 1e9, "iso8601": None}


@dataclass(frozen=True)
class CsvFormat:
    """How to read a CSV capture whose layout differs from the default;
    ``delimiter`` and ``decimal_comma`` ``None`` are detected from the file."""

    delimiter: str | None = None
    header: bool = True
    names: tuple[str, ...] | None = None
    columns: tuple[tuple[str, str], ...] = ()  # (CSV column name of docs/inputs.md, file column)
    sample_rate_hz: float | None = None
    pose_column: str | None = None
    skip_lines: int = 0
    comment_prefix: str | None = "#"
    decimal_comma: bool | None = None
    time_unit: str = "s"

    def file_column(self, name: str) -> str | None:
        """The file column read as the CSV column ``name``: with ``columns``
        given, only the ones it maps (a file's own ``gx`` is never taken as
        a reference by accident)."""
        if self.columns:
            return dict(self.columns).get(name)
        return name


@dataclass(frozen=True)
class CaptureSpec:
    """A ``[[capture]]`` entry: a file and the labels it lacks."""

    file: str
    axis: str | None = None
    rate_hz: float | None = None
    theta0_deg: float | None = None


@dataclass(frozen=True)
class DatasetMeta:
    """Resolved dataset metadata; ``notes`` say which defaults were applied."""

    device_id: str | None = None
    output_unit: str = "bit"
    full_scale: float | None = None
    cross_axis: float | None = None
    # [device] sensitivity, sensitivity_tolerance, offset_tolerance (``combine.datasheet``)
    datasheet: tuple[float | None, float | None, float | tuple[float, ...] | None] = (None, None, None)
    label_tolerance_deg: float = 4.0
    pose_means: bool = False
    g_local: float = STANDARD_GRAVITY
    g_local_uncertainty: float = STANDARD_GRAVITY_UNCERTAINTY
    g_local_source: str = "standard gravity (default)"
    angle_source: str = "commanded"
    csv_format: CsvFormat = field(default_factory=CsvFormat)
    imu_topic: str = "/imu"
    table_topic: str = "/table/joint_states"
    imu_topic_given: bool = False
    table_topic_given: bool = False
    plan_rates_hz: tuple[float, ...] = ()
    captures: tuple[CaptureSpec, ...] = ()
    source: str | None = None
    notes: tuple[str, ...] = ()
    identification: Identification = field(default_factory=Identification)  # the certificate's parts

    @property
    def placement(self) -> Placement:
        """What the static reduction takes from ``[device]`` and ``[format]`` about hand-placed poses."""
        return Placement(self.cross_axis, self.label_tolerance_deg, self.pose_means, *self.datasheet)


def _parse(text: str, path: Path, what: str = "dataset.toml") -> dict:
    try:
        return {key: _dates_as_text(value) for key, value in tomllib.loads(text).items()}
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{what} is not valid TOML: {exc}", path=path) from None
    except RecursionError:
        raise InputError(f"{what} has tables or arrays nested more than {MAX_NESTING} deep", path=path) from None
    except ValueError:  # int() refuses more than sys.get_int_max_str_digits() digits
        long = re.search(r"[0-9_]{4000,}", text)
        line = text.count("\n", 0, long.start()) + 1 if long else "?"
        raise InputError(f"{what} line {line}: an integer beyond the 64-bit range of TOML integers",
                         path=path) from None


def _dates_as_text(value: object) -> object:
    """TOML's dates and times as the ISO 8601 text the schema reads ([certificate] dates)."""
    if isinstance(value, dict):
        return {k: _dates_as_text(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_dates_as_text(v) for v in value]
    return value.isoformat() if isinstance(value, date | datetime | time) else value


def _check_values(doc: dict, path: Path, what: str = "dataset.toml") -> None:
    """Refuse what the schema's bounds let through: NaN and infinity (every
    comparison with NaN is false), integers beyond 64 bits, NUL characters
    (no file or column name holds one) and absurd nesting; in document order."""
    stack: list[tuple[tuple, object]] = [((), doc)]
    while stack:
        where, value = stack.pop()
        key = ".".join(map(str, where))
        if len(where) > MAX_NESTING:
            raise InputError(f"{what} has tables or arrays nested more than {MAX_NESTING} deep (at {key})", path=path)
        if isinstance(value, dict | list):
            items = value.items() if isinstance(value, dict) else enumerate(value)
            stack.extend(reversed([((*where, k), v) for k, v in items]))
        elif isinstance(value, float) and not math.isfinite(value):
            raise InputError(f"invalid {what} value: {key} = {value} is not a finite number", path=path)
        elif isinstance(value, int) and not isinstance(value, bool) and not -INT64 <= value < INT64:
            raise InputError(f"invalid {what} value: {key} is an integer beyond the 64-bit range of TOML integers",
                             path=path)
        elif isinstance(value, str) and "\0" in value:
            raise InputError(f"invalid {what} value: {key} holds a NUL character", path=path)


def _validate(doc: dict, path: Path, what: str = "dataset.toml") -> None:
    validator = jsonschema.Draft202012Validator(schema_text("dataset_toml"))
    errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
    if not errors:
        return
    err = errors[0]
    where = ".".join(str(p) for p in err.absolute_path) or "top level"
    if err.validator == "additionalProperties":
        extra = sorted(set(err.instance) - set(err.schema.get("properties", {})))
        problem = f"unknown key {extra[0]!r} in [{where}]" if where != "top level" else f"unknown table or key {extra[0]!r}"
    elif err.validator == "enum":
        problem = f"{where} = {err.instance!r} is not one of {err.validator_value}"
    elif err.validator == "propertyNames":
        problem = f"[{where}] maps an unknown column {err.instance!r}"
    else:
        problem = f"{where}: {err.message}"
    raise InputError(f"invalid {what} value: {problem}", path=path)


def load_meta(path: Path | None) -> DatasetMeta:
    """Read and validate a ``dataset.toml``; ``None`` gives the defaults."""
    if path is None:
        doc: dict = {}
    else:
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            raise InputError("dataset.toml not found", path=path) from None
        except UnicodeDecodeError as exc:
            raise InputError(f"dataset.toml is not valid TOML: {exc}", path=path) from None
        doc = _parse(text, path)
        _check_values(doc, path)
        _validate(doc, path)
    device, site, fmt = doc.get("device", {}), doc.get("site", {}), doc.get("format", {})
    mcap, plan = doc.get("mcap", {}), doc.get("plan", {})
    notes = []
    if "g_local" not in site:
        notes.append(
            f"g_local not given: using standard gravity {STANDARD_GRAVITY} m/s^2 "
            f"with standard uncertainty {STANDARD_GRAVITY_UNCERTAINTY} m/s^2"
        )
        g_u = STANDARD_GRAVITY_UNCERTAINTY
    else:
        g_u = float(site.get("g_local_uncertainty", 0.0))
        if "g_local_uncertainty" not in site:
            notes.append("g_local_uncertainty not given: g_local taken as exact")
    csv_format = CsvFormat(
        delimiter=DELIMITERS[fmt["delimiter"]] if "delimiter" in fmt else None,
        header=bool(fmt.get("header", True)),
        names=tuple(fmt["names"]) if "names" in fmt else None,
        columns=tuple(sorted(fmt.get("columns", {}).items())),
        sample_rate_hz=fmt.get("sample_rate_hz"),
        pose_column=fmt.get("pose_column"),
        skip_lines=int(fmt.get("skip_lines", 0)),
        comment_prefix=fmt.get("comment_prefix", "#") or None,
        decimal_comma={",": True, ".": False}.get(fmt.get("decimal", "")),
        time_unit=fmt.get("time_unit", "s"),
    )
    rate = csv_format.sample_rate_hz
    if rate is not None and not 1e-6 <= rate <= 1e9:
        # stamps are whole nanoseconds within +-9e9 s: beyond these every stamp is equal or out of range
        raise InputError(f"invalid dataset.toml value: [format] sample_rate_hz = {rate!r} puts the samples "
                         f"{1 / rate:.3g} s apart; rotcal reads rates of 1e-6 to 1e9 Hz (time stamps are whole "
                         "nanoseconds): the logger's rate in Hz?", path=path)
    if not csv_format.header and csv_format.names is None:
        raise InputError("invalid dataset.toml value: [format] header = false needs names = [...]", path=path)
    if "sensitivity_tolerance" in device and "sensitivity" not in device:
        raise InputError("invalid dataset.toml value: [device] sensitivity_tolerance needs sensitivity, the nominal "
                         "value it bounds (output unit per g, e.g. 16384 for an MPU-6050 at +-2 g)", path=path)
    files = [c["file"] for c in doc.get("capture", ())]
    twice = sorted({f for f in files if files.count(f) > 1})
    if twice:
        # read twice, every record would be a duplicate of itself
        raise InputError(f"invalid dataset.toml value: [[capture]] file {twice[0]!r} is named twice", path=path)
    return DatasetMeta(
        device_id=device.get("id"),
        output_unit=device.get("output_unit", "bit"),
        full_scale=device.get("full_scale"),
        cross_axis=device.get("cross_axis"),
        datasheet=(device.get("sensitivity"), device.get("sensitivity_tolerance"),
                   tuple(device["offset_tolerance"]) if isinstance(device.get("offset_tolerance"), list)
                   else device.get("offset_tolerance")),
        label_tolerance_deg=float(fmt.get("label_tolerance_deg", 4.0)),
        pose_means=bool(fmt.get("pose_means", False)),
        g_local=float(site.get("g_local", STANDARD_GRAVITY)),
        g_local_uncertainty=g_u,
        g_local_source=f"{path.name} [site]" if "g_local" in site and path is not None else DatasetMeta.g_local_source,
        angle_source=doc.get("angle_source", "commanded"),
        csv_format=csv_format,
        imu_topic=mcap.get("imu_topic", "/imu"),
        table_topic=mcap.get("table_topic", "/table/joint_states"),
        imu_topic_given="imu_topic" in mcap,
        table_topic_given="table_topic" in mcap,
        plan_rates_hz=tuple(float(r) for r in plan.get("rates_hz", ())),
        captures=tuple(CaptureSpec(**c) for c in doc.get("capture", ())),
        source=None if path is None else str(path),
        notes=tuple(notes),
        identification=identification_from_toml(doc, path),
    )
