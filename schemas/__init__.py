"""Resource package (installed as ``rotcal_schemas``): the JSON table and metadata contracts.

``schema_text`` reads one. It lives here, not in ``rotcal.tables`` (which
builds polars schemas from them), so that the batch process reads the
manifest's and ``dataset.toml``'s contracts without loading polars."""

from __future__ import annotations

import json
from importlib import resources


def schema_text(name: str) -> dict:
    """The parsed JSON document of a schema in ``schemas/``."""
    return json.loads(resources.files(__name__).joinpath(f"{name}.json").read_text())
