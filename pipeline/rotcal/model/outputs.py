"""The outputs registry: every file a run publishes, once, in the order it
is published, with its contract in ``schemas/`` and whether it describes
the input or is a result; and every other table contract (``CONTRACTS``)
with what writes it. ``model.results.Table`` and ``run.outputs`` refuse a
name this registry does not hold, ``run.outputs.publish`` writes in its
order, and ``tests/test_outputs_registry.py`` checks it against
``schemas/`` and against what a run writes.

It loads nothing (the batch process, which plans runs without polars,
may read it)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class Output:
    """One file of a run's output directory.

    ``name``: the item's name (``Table.name``, a figure's name), the stem of
    a table's file; ``file``: its file name in the output directory;
    ``role``: ``input`` for a table that describes the recording (published
    even when no rate can be determined, with the failure rows), ``result``
    otherwise; ``schema``: its contract in ``schemas/`` (a table's columns,
    or a JSON document's schema), None for a figure or a report."""

    name: str
    file: str
    role: Literal["input", "result"]
    schema: str | None

    @property
    def is_table(self) -> bool:
        return self.file.endswith(".parquet")


def _table(name: str, role: Literal["input", "result"] = "result") -> Output:
    return Output(name, f"{name}.parquet", role, name)


# the run's files in the order they are published (and listed in RunOutcome.written)
OUTPUTS: tuple[Output, ...] = (
    _table("segments", "input"),
    _table("fits", "input"),
    _table("timebase", "input"),
    _table("dwells", "input"),
    _table("diagnosis"),
    _table("effect_parameters"),
    Output("diagnosis_report", "report.md", "result", None),
    Output("calibration", "calibration.json", "result", "calibration"),
    _table("intrinsic"),
    _table("components"),
    _table("cross_sensitivity"),
    _table("correction"),
    _table("correction_uncertainty"),
    _table("correction_temperature"),
    _table("uncertainty_budget"),
    _table("simultaneous"),
    _table("consistency"),
    _table("gaitan_estimators"),
    _table("frequency_response"),
    Output("frequency_response_png", "frequency_response.png", "result", None),
    _table("monte_carlo"),
    _table("poses", "input"),
    _table("still_unused", "input"),
    _table("noise"),
    Output("noise_allan_png", "noise_allan.png", "result", None),
    # views of the files published before them: last
    Output("certificate", "certificate.html", "result", None),
    Output("certificate_pdf", "certificate.pdf", "result", None),
)


@dataclass(frozen=True)
class Contract:
    """A table contract of ``schemas/`` that a run does not publish, and
    what writes it (or that nothing does)."""

    name: str
    written_by: str


CONTRACTS: tuple[Contract, ...] = (
    Contract("samples", "nothing: the samples every stage reads, held in memory"),
    Contract("matrix_intrinsic", "rotcal intrinsic: <matrix>_intrinsic.parquet"),
    Contract("batch_datasets", "rotcal batch: manifest.sqlite"),
    Contract("batch_runs", "rotcal batch: manifest.sqlite"),
    Contract("batch_file_hashes", "rotcal batch: manifest.sqlite"),
    Contract("batch_combined", "rotcal batch: combined/<table>.parquet, every dataset's table with its path"),
)

_RANK = {o.name: k for k, o in enumerate(OUTPUTS)}
INPUT_TABLES = tuple(o.name for o in OUTPUTS if o.role == "input")


def output(name: str) -> Output:
    """The registry's entry ``name``; ``KeyError`` naming the registry for
    another name (a programming error: an output is registered before it is made)."""
    if name not in _RANK:
        raise KeyError(f"{name!r} is not a run output of rotcal.model.outputs.OUTPUTS")
    return OUTPUTS[_RANK[name]]


def publish_rank(name: str) -> int:
    """Where ``name`` is published among the run's files (0 first)."""
    output(name)
    return _RANK[name]


def table_contracts() -> frozenset[str]:
    """Every table contract the registry names: the run's tables and ``CONTRACTS``."""
    return frozenset(o.schema for o in OUTPUTS if o.is_table and o.schema) | {c.name for c in CONTRACTS}
