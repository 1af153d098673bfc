"""What a calibration certificate states beside the results (ISO/IEC
17025:2017 7.8.2.1 and 7.8.4.1): the laboratory, the customer, the item
calibrated and its settings, the equipment used and its traceability, and
the certificate's own facts (number, dates, place, environmental
conditions, approval).

Each is text the laboratory gives, in ``dataset.toml`` or in the site file
it keeps once (``ingest.site``), never made up: a field nobody gave is
``None`` here and "not given" on the certificate. The keys are those of
``schemas/dataset_toml.json``'s ``[laboratory]``, ``[customer]``,
``[item]``, ``[equipment]`` and ``[certificate]`` tables.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from datetime import date
from pathlib import Path
from typing import Any

from rotcal.errors import InputError

NOT_GIVEN = "not given"


@dataclass(frozen=True)
class Laboratory:
    name: str | None = None
    address: str | None = None
    accreditation: str | None = None


@dataclass(frozen=True)
class Customer:
    name: str | None = None
    address: str | None = None
    reference: str | None = None


@dataclass(frozen=True)
class Item:
    description: str | None = None
    make: str | None = None
    model: str | None = None
    serial_number: str | None = None
    range: str | None = None
    output_rate: str | None = None
    filter: str | None = None
    settings: str | None = None


@dataclass(frozen=True)
class Equipment:
    rotation_table: str | None = None
    angle_reference: str | None = None
    angle_traceability: str | None = None
    rate_reference: str | None = None
    rate_traceability: str | None = None
    clock_reference: str | None = None
    clock_traceability: str | None = None
    g_local_traceability: str | None = None


@dataclass(frozen=True)
class CertificateFacts:
    number: str | None = None
    date_of_issue: str | None = None
    date_of_measurement: str | None = None  # one day, or "first to last"
    place: str | None = None
    temperature: str | None = None
    humidity: str | None = None
    conditions: str | None = None
    approved_by: str | None = None
    function: str | None = None


PARTS: dict[str, type] = {"laboratory": Laboratory, "customer": Customer, "item": Item, "equipment": Equipment,
                          "certificate": CertificateFacts}
# what the certificate calls each field; those not in REQUIRED appear only when given
LABELS = {
    "laboratory": {"name": "laboratory", "address": "address", "accreditation": "accreditation"},
    "customer": {"name": "customer", "address": "address", "reference": "customer's reference"},
    "item": {"description": "item", "make": "make", "model": "model", "serial_number": "serial number",
             "range": "range", "output_rate": "output rate", "filter": "filter", "settings": "other settings"},
    "equipment": {"rotation_table": "rotation table", "angle_reference": "angle reference",
                  "angle_traceability": "angle traceability", "rate_reference": "rate reference",
                  "rate_traceability": "rate traceability", "clock_reference": "clock reference",
                  "clock_traceability": "clock traceability", "g_local_traceability": "g_local traceability"},
    "certificate": {"number": "certificate number", "date_of_issue": "date of issue",
                    "date_of_measurement": "date of measurement", "place": "place of calibration",
                    "temperature": "temperature", "humidity": "relative humidity", "conditions": "other conditions",
                    "approved_by": "approved by", "function": "function"},
}
OPTIONAL = {("laboratory", "accreditation"), ("customer", "reference"), ("item", "description"), ("item", "settings"),
            ("certificate", "conditions")}
# the certificate's own number and dates: one certificate's, never a site-wide default
PER_CERTIFICATE = ("number", "date_of_issue", "date_of_measurement")


@dataclass(frozen=True)
class SiteFile:
    """The site file a run read: where, and its content's SHA-256."""

    path: str
    sha256: str


@dataclass(frozen=True)
class Identification:
    """Everything the certificate states beside the results, as given."""

    laboratory: Laboratory = field(default_factory=Laboratory)
    customer: Customer = field(default_factory=Customer)
    item: Item = field(default_factory=Item)
    equipment: Equipment = field(default_factory=Equipment)
    certificate: CertificateFacts = field(default_factory=CertificateFacts)
    site_file: SiteFile | None = None

    def value(self, part: str, key: str) -> str:
        """A field's text, or "not given"."""
        given = getattr(getattr(self, part), key)
        return NOT_GIVEN if given is None else given

    def shown(self, part: str) -> list[tuple[str, str]]:
        """The (label, text) of ``part``'s fields the certificate shows: every
        required one (absent: "not given"), the optional ones when given."""
        record = getattr(self, part)
        return [(LABELS[part][f.name], self.value(part, f.name)) for f in dataclasses.fields(record)
                if (part, f.name) not in OPTIONAL or getattr(record, f.name) is not None]

    def over(self, defaults: Identification) -> Identification:
        """These fields, each absent one taken from ``defaults`` (the site file's)."""
        merged = {part: dataclasses.replace(getattr(defaults, part), **{
            k: v for k, v in dataclasses.asdict(getattr(self, part)).items() if v is not None}) for part in PARTS}
        return Identification(**merged, site_file=self.site_file or defaults.site_file)

    def to_dict(self) -> dict[str, Any]:
        """The given fields by part (calibration.json's ``certificate``)."""
        doc: dict[str, Any] = {part: {k: v for k, v in dataclasses.asdict(getattr(self, part)).items() if v is not None}
                               for part in PARTS}
        doc = {part: keys for part, keys in doc.items() if keys}
        if self.site_file is not None:
            doc["site_file"] = dataclasses.asdict(self.site_file)
        return doc

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> Identification:
        """The record of ``to_dict``'s document."""
        site = doc.get("site_file")
        # a later 1.x document's new fields are left out, not refused
        known = {part: {f.name for f in dataclasses.fields(kind)} for part, kind in PARTS.items()}
        return cls(**{part: kind(**{k: v for k, v in doc.get(part, {}).items() if k in known[part]})
                      for part, kind in PARTS.items()},
                   site_file=None if site is None else SiteFile(**site))


def _day(text: str, key: str, path: Path | None, what: str) -> date:
    try:
        return date.fromisoformat(text)
    except ValueError:
        raise InputError(f"invalid {what} value: certificate.{key} = {text!r} is not a calendar date", path=path) from None


def identification_from_toml(doc: dict[str, Any], path: Path | None, what: str = "dataset.toml") -> Identification:
    """The parts of a TOML document already valid against
    ``schemas/dataset_toml.json`` (dates as ISO strings), with the checks a
    schema cannot make: real calendar days, a measurement's first day not
    after its last, and no date of issue before the measurement ended."""
    parts = {part: kind(**doc.get(part, {})) for part, kind in PARTS.items()}
    cert = doc.get("certificate", {})
    measured = cert.get("date_of_measurement")
    days = [measured] if isinstance(measured, str) else list(measured or [])
    span = [_day(d, "date_of_measurement", path, what) for d in days]
    if len(span) == 2 and span[0] > span[1]:
        raise InputError(f"invalid {what} value: certificate.date_of_measurement runs from {days[0]} back to {days[1]}",
                         path=path)
    if "date_of_issue" in cert:
        issued = _day(cert["date_of_issue"], "date_of_issue", path, what)
        if span and issued < span[-1]:
            raise InputError(f"invalid {what} value: certificate.date_of_issue {cert['date_of_issue']} is before the "
                             f"measurement ended ({days[-1]})", path=path)
    if len(days) == 2:
        text = days[0] if days[0] == days[1] else f"{days[0]} to {days[1]}"
        parts["certificate"] = dataclasses.replace(parts["certificate"], date_of_measurement=text)
    return Identification(**parts)
