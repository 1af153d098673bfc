"""The outputs registry (``rotcal.model.outputs``) against what it lists:
every table contract in ``schemas/`` is in it, every file a run writes is
one of its entries, in its order, under its schema; an item it does not
name is refused when it is made."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import polars as pl
import pytest

from rotcal.config import RunConfig
from rotcal.model.outputs import CONTRACTS, INPUT_TABLES, OUTPUTS, output, table_contracts
from rotcal.model.results import Table
from rotcal.report.publish import LISTING
from rotcal.run import run_dataset
from rotcal.run.outputs import Figure
from rotcal.tables import read_schema_name

SCHEMAS = Path(__file__).resolve().parents[1] / "schemas"


def _table_schemas() -> set[str]:
    """The contracts of ``schemas/`` that are tables (they list columns), not JSON documents."""
    return {p.stem for p in SCHEMAS.glob("*.json") if "columns" in json.loads(p.read_text())}


def test_every_table_schema_is_in_the_registry_and_every_entry_has_its_schema():
    tables = _table_schemas()
    assert len(tables) >= 25  # the glob found the contracts
    assert tables == table_contracts()
    documents = {p.stem for p in SCHEMAS.glob("*.json")}
    assert {o.schema for o in OUTPUTS if o.schema} <= documents
    names = [o.name for o in OUTPUTS] + [c.name for c in CONTRACTS]
    assert len(names) == len(set(names))
    assert len({o.file for o in OUTPUTS}) == len(OUTPUTS)


def test_the_input_tables_are_those_published_when_nothing_is_determined():
    assert INPUT_TABLES == ("segments", "fits", "timebase", "dwells", "poses", "still_unused")
    assert [o.name for o in OUTPUTS[-2:]] == ["certificate", "certificate_pdf"]  # views of the files before them


def test_an_item_the_registry_does_not_name_is_refused():
    with pytest.raises(KeyError, match="OUTPUTS"):
        Table("noise_floor", pl.DataFrame())
    with pytest.raises(KeyError, match="not a table"):
        Table("calibration", pl.DataFrame())
    with pytest.raises(KeyError, match="is a table"):
        Figure("intrinsic", lambda out: None)


def test_every_file_a_run_writes_is_in_the_registry_in_its_order(make_dataset, tmp_path):
    """The demo's dataset with the demo's configuration (every table, the Monte Carlo included)."""
    config = replace(RunConfig(), uncertainty=replace(RunConfig().uncertainty, monte_carlo=True))
    outcome = run_dataset(make_dataset(1), tmp_path / "out", None, config)
    written = [p.relative_to(tmp_path / "out") for p in outcome.written]
    by_file = {o.file: o for o in OUTPUTS}
    named = [by_file[str(p)] for p in written if str(p) in by_file]
    # the report's figures sit in figures/ beside report.md, the listing is report.publish's
    assert {str(p) for p in written} - set(by_file) <= {LISTING} | {str(p) for p in written if p.parts[0] == "figures"}
    assert [o.name for o in named] == sorted((o.name for o in named), key=lambda n: OUTPUTS.index(output(n)))
    parquet = sorted((tmp_path / "out").glob("*.parquet"))
    assert len(parquet) >= 15
    for path in parquet:
        entry = by_file[path.name]
        assert entry.is_table and read_schema_name(path)[0] == entry.schema
