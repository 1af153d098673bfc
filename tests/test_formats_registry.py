"""The capture formats' one registry (``rotcal.ingest.formats``): no other
module of the package decides a format by a file's suffix, every format's
reader, writer and block reader are where the registry says, and a
capture written by a format's writer reads back as the samples written."""

from __future__ import annotations

import ast
from dataclasses import replace
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from polars.testing import assert_frame_equal

from rotcal.config import Limits
from rotcal.ingest import formats
from rotcal.ingest.dataset import read_capture
from rotcal.ingest.meta import load_meta
from rotcal.simulate import SimulationSpec, simulate

PACKAGE = Path(__file__).resolve().parents[1] / "pipeline" / "rotcal"
REGISTRY_FILE = PACKAGE / "ingest" / "formats" / "__init__.py"


def suffix_tests(source: str, suffixes: tuple[str, ...]) -> list[tuple[int, str]]:
    """String literals that name a capture suffix on their own (``".mcap"``,
    ``"*.csv"``, any case): what a suffix comparison, a suffix list or a
    glob for captures is written with. A file name (``"capture.mcap"``) or
    a sentence is not one, nor the end of a file name built by an f-string."""
    wanted = {s.lower() for s in suffixes} | {f"*{s.lower()}" for s in suffixes}
    tree = ast.parse(source)
    built = {id(part) for node in ast.walk(tree) if isinstance(node, ast.JoinedStr) for part in node.values}
    return [(node.lineno, node.value) for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and node.value.lower() in wanted and id(node) not in built]


def test_no_suffix_test_outside_the_registry():
    found = {str(p.relative_to(PACKAGE)): hits for p in sorted(PACKAGE.rglob("*.py")) if p != REGISTRY_FILE
             and (hits := suffix_tests(p.read_text(), formats.SUFFIXES))}
    assert not found, f"decide a capture's format with rotcal.ingest.formats, not by its suffix: {found}"


def test_the_finder_finds_suffix_tests():
    """What a format question looks like outside the registry is found; file names and prose are not."""
    source = ('if path.suffix.lower() == ".mcap": pass\nSUFFIXES = (".csv", ".MCAP")\nfiles = d.glob("*.mcap")\n'
              'name = "capture.mcap"\n"""no capture files (*.csv, *.mcap)"""\nsegment = f"{k:02d}_x.csv"\n')
    assert [v for _, v in suffix_tests(source, formats.SUFFIXES)] == [".mcap", ".csv", ".MCAP", "*.mcap"]


def test_every_entry_loads_what_it_names():
    assert len({f.suffix for f in formats.REGISTRY}) == len(formats.REGISTRY)
    for fmt in formats.REGISTRY:
        assert fmt.suffix == fmt.suffix.lower() and fmt.suffix.startswith(".")
        assert callable(fmt.reader)
        assert fmt.writer is None or callable(fmt.writer)
        assert fmt.can_stream == (fmt.block_reader is not None)
    assert formats.format_of("a/B.MCAP") is formats.by_name("mcap")
    assert formats.format_of("notes.txt") is None and not formats.is_capture("notes.txt")
    assert formats.named_format("logger.txt") is formats.NAMED_DEFAULT is formats.by_name("csv")


SPEC = SimulationSpec()
SPEC = replace(SPEC, plan=replace(SPEC.plan, rotation_samples=300, rates_hz=(0.5,)))


@pytest.mark.parametrize("fmt", [f for f in formats.REGISTRY if f.writes is not None], ids=lambda f: f.name)
def test_a_written_capture_reads_back(tmp_path, fmt):
    """A seeded simulation's samples (t_ns, u, v, w) through a format's
    writer and reader: the same stamps and outputs, bit for bit."""
    samples = simulate(SPEC, 5).samples.select("t_ns", "u", "v", "w")
    path = fmt.writer(samples, tmp_path / f"capture{fmt.suffix}")
    frame, _ = read_capture(path, None, load_meta(None), Limits())
    assert_frame_equal(frame.select("t_ns", "u", "v", "w"), samples, check_dtypes=False)
    assert np.array_equal(frame["t_ns"].to_numpy(), samples["t_ns"].to_numpy())
    assert frame.schema["t_ns"] == pl.Int64
