"""Table contracts: load the JSON schemas of ``schemas/``, conform frames to
them, and write Parquet files atomically with the schema recorded in the file.

A schema file holds ``name``, ``version``, ``description`` and ``columns``
(each with ``name``, ``type``, ``description`` and, where it has one,
``unit``). Types are ``string``, ``bool``, ``int32``, ``int64``,
``float64`` and ``list[float64]``; internal tables (``samples``) may also use
``enum`` (with ``values``) and ``categorical``, one integer code a row for
label columns of millions of rows.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import TYPE_CHECKING

import polars as pl

from rotcal import __version__
from rotcal_schemas import schema_text

if TYPE_CHECKING:
    import pyarrow as pa

_DTYPES: dict[str, pl.DataType] = {
    "string": pl.String(),
    "bool": pl.Boolean(),
    "int32": pl.Int32(),
    "int64": pl.Int64(),
    "float64": pl.Float64(),
    "list[float64]": pl.List(pl.Float64()),
}


@dataclass(frozen=True)
class TableSchema:
    """One table contract from ``schemas/<name>.json``."""

    name: str
    version: str
    columns: tuple[str, ...]
    dtypes: tuple[pl.DataType, ...]

    @property
    def polars_schema(self) -> dict[str, pl.DataType]:
        return dict(zip(self.columns, self.dtypes))

    def empty(self) -> pl.DataFrame:
        return pl.DataFrame(schema=self.polars_schema)


@cache
def schema(name: str) -> TableSchema:
    doc = schema_text(name)
    cols = doc["columns"]
    return TableSchema(
        name=doc["name"],
        version=doc["version"],
        columns=tuple(c["name"] for c in cols),
        dtypes=tuple(_dtype(c) for c in cols),
    )


def _dtype(column: dict) -> pl.DataType:
    if column["type"] == "enum":
        return pl.Enum(column["values"])
    if column["type"] == "categorical":
        return pl.Categorical()
    return _DTYPES[column["type"]]


def _require_columns(frame: pl.DataFrame, name: str) -> TableSchema:
    """Contract ``name``, which ``frame`` has every column of; else ``KeyError`` naming the missing ones."""
    sch = schema(name)
    present = set(frame.columns)  # a list built anew at each access: once, not per column
    missing = [c for c in sch.columns if c not in present]
    if missing:
        raise KeyError(f"table {name!r} lacks columns {missing}")
    return sch


def conform(frame: pl.DataFrame, name: str) -> pl.DataFrame:
    """Select and cast ``frame``'s columns to the contract ``name``, in its order.

    Raises ``KeyError`` naming the missing columns: a missing column is a
    programming error, not a user's.
    """
    sch = _require_columns(frame, name)
    if frame.columns == list(sch.columns) and frame.dtypes == list(sch.dtypes):
        return frame  # as the select would give it, without its query (0.2 ms: most frames are built conforming)
    return frame.select(pl.col(c).cast(t, strict=True) for c, t in zip(sch.columns, sch.dtypes))


def parquet_metadata(name: str) -> dict[bytes, bytes]:
    sch = schema(name)
    return {
        b"rotcal.schema": sch.name.encode(),
        b"rotcal.schema_version": sch.version.encode(),
        b"rotcal.version": __version__.encode(),
    }


def atomic_write(path: Path, write: Callable[[Path], object]) -> Path:
    """``write`` a temporary file beside ``path``, then move it over ``path``
    (rename(2) is atomic within one file system): no reader ever sees half
    a file, and an error leaves none. Every file rotcal writes goes through here."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _finite(column: pl.Expr, dtype: pl.DataType) -> pl.Expr:
    """``column`` (of type ``dtype``) with every NaN or infinite float, alone
    or a list's element (a failed fit's covariance), made null (missing);
    other types as they are."""
    if dtype in (pl.Float64, pl.Float32):
        return pl.when(column.is_finite()).then(column).otherwise(None)
    if isinstance(dtype, pl.List) and dtype.inner in (pl.Float64, pl.Float32):
        return column.list.eval(pl.when(pl.element().is_finite()).then(pl.element()))
    return column


def finite_or_null(frame: pl.DataFrame) -> pl.DataFrame:
    """Every NaN or infinite float of ``frame`` published as null (missing):
    nothing non-finite is ever published. Where a column means something by
    it (infinite degrees of freedom), its schema description says so."""
    return frame.with_columns(_finite(pl.col(c), dtype).alias(c) for c, dtype in frame.schema.items())


@cache
def _published_columns(name: str) -> tuple[pl.Expr, ...]:
    """The one projection that publishes a frame as contract ``name``: each
    column cast to its type (strictly) and made finite or null
    (``finite_or_null``). Built once a process per contract."""
    sch = schema(name)
    return tuple(_finite(pl.col(c).cast(t, strict=True), t).alias(c) for c, t in zip(sch.columns, sch.dtypes))


def contract_table(frame: pl.DataFrame, name: str) -> pa.Table:
    """``frame`` as the Arrow table of contract ``name``: its columns in the
    contract's order and types, nothing non-finite (``finite_or_null``, in
    the same pass: ``_published_columns``), the schema named in its
    metadata. Raises ``KeyError`` naming missing columns (a programming error)."""
    _require_columns(frame, name)
    table = frame.select(_published_columns(name)).to_arrow()
    return table.replace_schema_metadata({**(table.schema.metadata or {}), **parquet_metadata(name)})


# How every table is encoded: one row group of a few hundred rows, so no
# dictionary pages (a float column's values are nearly all distinct, and
# dictionary attempts cost more than the encoding) and no column statistics
# (nothing to skip inside a file that small); snappy, the format's default
# codec, where zstd cost about twice the encoding for files a tenth larger.
# Tables read back the same whatever the encoding; these fixed options keep the
# bytes deterministic. Measured per dataset of 15 tables: 3.9 ms against
# 10 ms with zstd, dictionaries and statistics (docs/measured.md).
PARQUET_OPTIONS: dict[str, object] = {"compression": "snappy", "use_dictionary": False, "write_statistics": False}


def write_table(table: pa.Table, path: Path) -> Path:
    """Write an Arrow table to ``path`` as Parquet (``PARQUET_OPTIONS``),
    atomically (``atomic_write``). Encoded in memory and written with one
    call: the same bytes as ``pq.write_table`` to the path, without the
    cost of pyarrow's file sink, which for a small table exceeds the encoding."""
    import pyarrow as pa  # loaded at the first write: not held through the stages before (memory)
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink, **PARQUET_OPTIONS)
    path.parent.mkdir(parents=True, exist_ok=True)
    return atomic_write(path, lambda tmp: tmp.write_bytes(sink.getvalue()))


def write_parquet(frame: pl.DataFrame, path: Path, name: str) -> Path:
    """Write ``frame`` as contract ``name`` to ``path``, atomically (``atomic_write``)."""
    return write_table(contract_table(frame, name), path)


def read_schema_name(path: Path) -> tuple[str, str]:
    """The (schema name, schema version) recorded in a Parquet file rotcal wrote."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(path).metadata or {}
    return meta[b"rotcal.schema"].decode(), meta[b"rotcal.schema_version"].decode()
