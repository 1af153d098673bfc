"""One corrupt dataset among 50: 49 results, one quarantine entry with its
reason, exit status 4; the combined dataset read by polars, pyarrow and
DuckDB agrees with the per-dataset tables."""

import duckdb
import jsonschema
import polars as pl
import pyarrow.dataset as pads

from rotcal.batch.plan import dataset_id
from rotcal_schemas import schema_text

from batch_support import assert_clean, config_file, make_root, manifest_rows


def test_one_corrupt_dataset_among_fifty(cli, tmp_path):
    root, out = tmp_path / "root", tmp_path / "out"
    paths = make_root(root, range(1, 51))
    bad = paths[17]
    victim = sorted((root / bad).glob("*_0.5hz.csv"))[0]
    lines = victim.read_text().splitlines()
    lines[40] = lines[40].replace(",", ",oops", 1)
    victim.write_text("\n".join(lines) + "\n")

    status, stdout, err = cli("batch", root, "--out", out, "--workers", "2", "--json", "--config", config_file(tmp_path))
    summary = __import__("json").loads(stdout)
    jsonschema.validate(summary, schema_text("batch_summary"))
    assert status == 4, err
    assert (summary["discovered"], summary["ok"], summary["quarantined"], summary["errors"]) == (50, 49, 1, 0)
    assert summary["workers"] == 2 and summary["exit_status"] == 4
    [problem] = summary["problems"]
    assert problem["dataset_path"] == bad and problem["status"] == "quarantined"
    assert victim.name in problem["reason"] and "row 40" in problem["reason"] and "is not a number" in problem["reason"]
    rows = manifest_rows(out)
    assert sorted(r["status"] for r in rows.values()) == ["ok"] * 49 + ["quarantined"]
    assert rows[bad]["reason"] == problem["reason"]
    assert len(list((out / "datasets").iterdir())) == 49
    assert_clean(out)

    glob = str(out / "combined" / "intrinsic" / "*.parquet")
    by_polars = pl.scan_parquet(out / "combined" / "intrinsic").collect()
    by_arrow = pl.from_arrow(pads.dataset(out / "combined" / "intrinsic", format="parquet").to_table())
    by_duckdb = duckdb.sql(f"SELECT * FROM read_parquet('{glob}')").pl()
    key = ["dataset_path", "rate_hz", "parameter"]
    for frame in (by_arrow, by_duckdb):
        assert frame.sort(key).equals(by_polars.sort(key))
    assert by_polars["dataset_path"].n_unique() == 49 and bad not in by_polars["dataset_path"].to_list()
    counts = duckdb.sql(f"SELECT dataset_path, count(*) AS n FROM read_parquet('{glob}') GROUP BY 1").pl()
    assert set(counts["n"]) == {18}  # 9 parameters at the static and the 0.5 Hz result
    own = pl.read_parquet(out / "datasets" / dataset_id(paths[3]) / "intrinsic.parquet")
    mine = by_polars.filter(pl.col("dataset_path") == paths[3]).drop("dataset_path")
    assert mine.sort(key[1:]).equals(own.sort(key[1:]))
    tables = {p.stem for p in (out / "datasets" / dataset_id(paths[3])).glob("*.parquet")}
    assert {p.name for p in (out / "combined").iterdir()} == tables >= {"components", "fits", "intrinsic", "segments"}
    for table in tables:
        assert len(list((out / "combined" / table).glob("*.parquet"))) == 49
