"""``rotcal demo`` writes every table of issue 3 and the frequency-response
plot, each with its schema recorded."""

import polars as pl

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
    assert "[plan], [dut], [site], [timebase], [[effect]]" in out
