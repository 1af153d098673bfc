"""Route by evidence: dwells chained about one axis are a table's step
sequence only where their directions lie on one great circle, turned by
equal steps (``segment.blind.table_steps``); poses stepped about one axis
by hand (irregular angles, a few degrees of wobble, no samples logged
while turning) take the pose route."""

from __future__ import annotations

import numpy as np
import polars as pl

from rotcal.model.physics import rotation_matrix
from rotcal.segment.blind import segment_blind

from posesim import hand_placed


def _about_z(angles_deg: np.ndarray, wobble_deg: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = np.column_stack([np.cos(np.radians(angles_deg)), np.sin(np.radians(angles_deg)), np.zeros(angles_deg.size)])
    if wobble_deg:
        d = np.array([rotation_matrix(np.cross(v, rng.standard_normal(3)), rng.uniform(0, wobble_deg)) @ v for v in d])
    return d


def _sequences(directions: np.ndarray, seed: int) -> tuple:
    sim = hand_placed(seed, directions=directions, samples=300, move_samples=0)
    return segment_blind(sim.t_ns, sim.y).sequences


def test_hand_steps_about_one_axis_are_poses():
    """Fourteen rests turned by 15 to 50 degrees about z, each wobbling up
    to 3 degrees: no step sequence, in each of five sessions."""
    for seed in range(5):
        rng = np.random.default_rng(200 + seed)
        angles = np.cumsum(rng.uniform(15, 50, 14))
        assert _sequences(_about_z(angles, 3.0, seed), seed) == (), seed


def test_a_tables_steps_keep_the_table_route():
    """Twelve 30-degree steps about z (a table's program, no wobble): one
    step sequence of all twelve dwells about the DUT's w axis."""
    sequences = _sequences(_about_z(np.arange(12) * 30.0, 0.0, 0), 0)
    assert len(sequences) == 1 and len(sequences[0].dwells) == 12 and sequences[0].axis == "z"


def test_the_route_and_its_evidence_are_printed(cli, tmp_path):
    """Two sessions' rests stepped about one axis by hand, through ``rotcal
    run``: the static route, its note naming the chains about one axis that
    lacked a table's steps."""
    from posesim import G_LOCAL, samples_frame

    rng = np.random.default_rng(200)
    sim = hand_placed(0, directions=_about_z(np.cumsum(rng.uniform(15, 50, 14)), 3.0, 0), samples=300, move_samples=0)
    data = tmp_path / "data"
    data.mkdir()
    samples_frame(sim).write_csv(data / "s.csv")
    (data / "dataset.toml").write_text(f'[device]\noutput_unit = "count"\n\n[site]\ng_local = {G_LOCAL}\n')
    status, out, err = cli("run", data, "--out", tmp_path / "out")
    printed = " ".join((out + err).split())
    assert status == 0, err
    assert "route: static poses, the signals showing no table segments (0 constant rotations, 0 static step sequences, " in printed
    assert "without a table's steps" in printed


def test_dwells_no_result_uses_are_counted():
    """A table recording whose step sequences give the static result: the
    dwells outside every sequence (segments of one pose) are not used, and
    a warning says how many (dwells.parquet lists them)."""
    from rotcal.combine.unreferenced import reduce_dwells
    from rotcal.tables import schema

    dwells = schema("dwells").empty().vstack(pl.DataFrame({"segment": [0, 0, 0, 4, 5]}).with_columns(
        *(pl.lit(None, dtype).alias(name) for name, dtype in schema("dwells").polars_schema.items() if name != "segment")
    ).select(schema("dwells").polars_schema.keys()).cast(schema("dwells").polars_schema))
    used = reduce_dwells(dwells, False, 9.81, 0.0, frozenset({4, 5}))
    assert used.warnings == ("2 of the 5 still intervals found are not used (still_unused.parquet lists each with its "
                             "reason): 2 a single pose outside every step sequence, which give the static result "
                             "(dwells.parquet lists it with its segment)",)
    assert {t.name: t.data.height for t in used.tables} == {"dwells": 5, "still_unused": 2}
    assert reduce_dwells(dwells, False, 9.81, 0.0, frozenset()).warnings == ()
