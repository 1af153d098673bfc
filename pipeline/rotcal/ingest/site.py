"""The site file: what a laboratory states on every certificate, kept once
(docs/outputs.md#how-a-laboratory-fills-in-the-fields). It holds ``[laboratory]``,
``[equipment]`` and ``[certificate]`` defaults (place, conditions,
approval; never the number or the dates, which are one certificate's), with
the keys and checks of ``dataset.toml`` (``schemas/dataset_toml.json``); a
dataset's own ``dataset.toml`` overrides it field by field.

Which file: ``[report] site`` (``--site``) when given; otherwise
``site.toml`` in the folder holding the dataset (``rotcal run``), or in the
batch's ROOT (``rotcal batch``); none is no error: the certificate then
shows the laboratory's fields as not given."""

from __future__ import annotations

import hashlib
from pathlib import Path

from rotcal.errors import InputError
from rotcal.ingest.meta import _check_values, _parse, _validate
from rotcal.model.identification import PER_CERTIFICATE, Identification, SiteFile, identification_from_toml

SITE_FILE = "site.toml"
SITE_PARTS = ("laboratory", "equipment", "certificate")


def site_path(dataset: Path, given: str) -> Path | None:
    """The site file of a run on ``dataset``: ``given`` (``[report] site``),
    else ``site.toml`` beside the dataset, else none."""
    if given:
        return Path(given)
    beside = Path(dataset).resolve().parent / SITE_FILE
    return beside if beside.is_file() else None


def load_site(path: Path | None) -> Identification:
    """The site file's fields (none: an empty record), validated as
    ``dataset.toml`` is and refused, in one line naming the file, for a part
    or key a site file does not hold."""
    if path is None:
        return Identification()
    try:
        data = Path(path).read_bytes()
    except FileNotFoundError:
        raise InputError("site file not found", path=path) from None
    except OSError as exc:
        raise InputError(f"site file cannot be read: {exc.strerror}", path=path) from None
    what = "site file"
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{what} is not valid TOML: {exc}", path=path) from None
    doc = _parse(text, path, what)
    _check_values(doc, path, what)
    other = sorted(set(doc) - set(SITE_PARTS))
    if other:
        raise InputError(f"invalid {what} value: [{other[0]}] belongs in dataset.toml (a site file holds "
                         f"{', '.join(f'[{p}]' for p in SITE_PARTS)})", path=path)
    own = [k for k in PER_CERTIFICATE if k in doc.get("certificate", {})]
    if own:
        raise InputError(f"invalid {what} value: certificate.{own[0]} is one certificate's: give it in dataset.toml",
                         path=path)
    _validate(doc, path, what)
    found = identification_from_toml(doc, path, what)
    return Identification(found.laboratory, found.customer, found.item, found.equipment, found.certificate,
                          SiteFile(str(Path(path).resolve()), hashlib.sha256(data).hexdigest()))
