"""How rotcal writes a JSON document a person may read (calibration.json,
the JSON export, a run's file listing): one key a line, and each list of
numbers or strings on one line, so a matrix reads as its rows."""

from __future__ import annotations

import json
from typing import Any

# Hand-written beside json.dumps(indent=...), which switches to the
# pure-Python encoder: a default-plan calibration.json (83 kB, some 2,000
# numbers) took 8.9 ms that way, against 1.3 ms for the C encoder without
# indentation. Here the C encoder writes every list of scalars whole.
_ENCODE = json.JSONEncoder(allow_nan=False).encode


def json_text(doc: Any) -> str:
    """``doc`` as JSON text ending in a newline: objects one key a line
    (indented by one space a level), lists of scalars on one line, lists
    holding lists or objects one item a line. Non-finite numbers raise
    ``ValueError`` (never published). Keys must be strings."""

    def text(value: Any, pad: str) -> str:
        inner = pad + " "
        if isinstance(value, dict) and value:
            items = (f"{inner}{_ENCODE(key)}: {text(item, inner)}" for key, item in value.items())
        elif isinstance(value, list | tuple) and any(isinstance(item, dict | list | tuple) for item in value):
            items = (inner + text(item, inner) for item in value)
        else:
            return _ENCODE(value)
        opening, closing = ("{", "}") if isinstance(value, dict) else ("[", "]")
        return f"{opening}\n" + ",\n".join(items) + f"\n{pad}{closing}"

    return text(doc, "") + "\n"
