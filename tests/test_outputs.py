"""``rotcal demo`` writes every table of issue 3 and the frequency-response
plot, each with its schema recorded."""

import polars as pl
import pytest

from rotcal.tables import read_schema_name

TABLES = ("uncertainty_budget", "monte_carlo", "simultaneous", "consistency", "gaitan_estimators", "frequency_response")


def test_demo_writes_every_table_and_the_png(cli, tmp_path):
    code, out, err = cli("demo", "--dir", tmp_path)
    assert code == 0, err
    results = tmp_path / "results"
    for name in TABLES:
        path = results / f"{name}.parquet"
        assert read_schema_name(path)[0] == name
        assert pl.read_parquet(path).height > 0
    assert (results / "frequency_response.png").read_bytes()[:4] == b"\x89PNG"
    assert "Monte Carlo (GUM Supplement 1) validates" in " ".join(err.split())
    mc = pl.read_parquet(results / "monte_carlo.parquet")
    assert mc.height == 45 and mc["stabilised"].all()
    assert "±" in out  # expanded uncertainties in the summary


def test_help_names_the_simulation_tables(cli):
    """rich reads "[plan]" in help text as markup and drops it; the help must
    still name the TOML tables a simulation file may hold."""
    code, out, _ = cli("simulate", "--help")
    assert code == 0
    assert "[plan], [dut], [site], [timebase], [noise], [[effect]]" in out


def test_nothing_non_finite_is_published(tmp_path):
    """NaN and infinities are written as null, whatever the stage handed over."""
    import numpy as np

    from rotcal.tables import schema as table_schema
    from rotcal.tables import write_parquet

    frame = pl.DataFrame({"dataset": ["d"] * 3, "model": ["baseline"] * 3, "recommended": [True] * 3, "rate_hz": [0.0] * 3, "parameter": ["s_u", "s_v", "s_w"],
                          "value": [1.0, np.nan, np.inf], "std_uncertainty": [0.1, 0.2, -np.inf], "dof": [np.inf, 5.0, 6.0],
                          "coverage_factor": [1.96, 2.57, 2.45], "expanded_uncertainty": [0.2, 0.5, np.nan], "unit": ["1"] * 3},
                         schema=table_schema("intrinsic").polars_schema)
    back = pl.read_parquet(write_parquet(frame, tmp_path / "intrinsic.parquet", "intrinsic"))
    assert back["value"].to_list() == [1.0, None, None]
    assert back["std_uncertainty"].to_list() == [0.1, 0.2, None]
    assert back["dof"].to_list() == [None, 5.0, 6.0]
    assert back["expanded_uncertainty"].to_list() == [0.2, 0.5, None]


def test_non_finite_list_elements_are_published_as_null(tmp_path):
    """A failed fit's covariance (list columns): each NaN or infinite
    element null, the finite ones and the list's length kept; an integer
    column given as floats is cast to its contract's type."""
    import numpy as np

    from rotcal.tables import schema as table_schema
    from rotcal.tables import write_parquet

    sch = table_schema("fits")
    row = {c: None for c in sch.columns} | {"segment": 3.0, "dof": 7.0, "C": np.nan,
                                              "cov_u": [1.0, np.nan, 2.0], "cov_v": [np.inf, -np.inf], "cov_w": []}
    frame = pl.DataFrame([row], schema=sch.polars_schema | {"segment": pl.Float64, "dof": pl.Float64})
    back = pl.read_parquet(write_parquet(frame, tmp_path / "fits.parquet", "fits"))
    assert back.schema == pl.Schema(sch.polars_schema)
    assert back.row(0, named=True) | {} == row | {"segment": 3, "dof": 7, "C": None, "cov_u": [1.0, None, 2.0], "cov_v": [None, None]}


def test_conform_casts_reorders_and_refuses():
    from rotcal.tables import conform, schema

    sch = schema("components")
    typed = pl.DataFrame({c: pl.Series([], dtype=t) for c, t in zip(sch.columns, sch.dtypes)})
    assert conform(typed, "components") is typed  # already the contract's: as it is
    floats = [c for c, t in zip(sch.columns, sch.dtypes) if t == pl.Float64]
    as_ints = typed.with_columns(pl.col(c).cast(pl.Int64) for c in floats)  # same order, other types
    reordered = typed.select(reversed(sch.columns)).with_columns(pl.lit(1).alias("extra"))
    for loose in (as_ints, reordered):
        out = conform(loose, "components")
        assert out.columns == list(sch.columns) and out.dtypes == list(sch.dtypes)
    with pytest.raises(KeyError, match=sch.columns[0]):
        conform(typed.drop(sch.columns[0]), "components")
