"""Where the tests find their data: the checkout, the real recordings in
../shared/data/real (``ROTCAL_SHARED`` moves it; tests that read them carry
``@pytest.mark.real`` and skip when it is absent) and the truth written
beside every simulated dataset.

Imported by plain name (``from testdata import REAL``): pyproject.toml puts
tests/ on pytest's ``pythonpath``, so this works under ``pytest`` and
``python -m pytest`` alike."""

from __future__ import annotations

import json
import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("ROTCAL_SHARED", REPO.parent / "shared"))
REAL = SHARED / "data" / "real"


def truth_of(dataset: Path) -> dict:
    """The simulator's truth.json of a simulated dataset directory."""
    return json.loads((dataset / "truth.json").read_text())
