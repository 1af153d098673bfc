"""The facts the stages need of an effect live on the effect
(``rotcal.model.effects``): what a DUT at rest shows of it, whether a
rotation's own-phase fit absorbs it. The diagnosis reads them there and
names no effect itself."""

from __future__ import annotations

import ast
from pathlib import Path

from rotcal.diagnose.static_model import _STEP
from rotcal.model.effects import catalogue, names

DIAGNOSE = Path(__file__).resolve().parents[1] / "pipeline" / "rotcal" / "diagnose"


def test_what_a_dut_at_rest_shows():
    """docs/method.md's static pose model: m = O + rho (t - t0) + tco (T -
    T_ref) + (1 + tcs (T - T_ref)) y (1 + k2 u) (1 + k3 u^2)."""
    at_rest = {e.name: e.at_rest for e in catalogue() if e.at_rest is not None}
    assert at_rest == {"cubic_nonlinearity": "pose", "quadratic_nonlinearity": "pose", "offset_drift": "time",
                       "thermal": "temperature"}
    # each of those effects' internal parameters has its central-difference step
    assert set(_STEP) == {"k2", "k3", "drift", "tco", "tcs"}
    untested = {e.name: e.not_at_rest for e in catalogue() if e.at_rest is None}
    assert untested["clipping"] == "not tested on static poses"  # found from stuck runs, not a pose model
    assert "rotation" in untested["rate_error"]


def test_what_an_own_phase_fit_absorbs():
    """A rotation fitted against its own phase takes the rate the samples
    show: a rate error of the table (or the logger's clock) is absorbed."""
    assert {e.name for e in catalogue() if e.absorbed_by_own_phase} == {"rate_error"}


def _named_effects(tree: ast.AST, effects: frozenset[str]) -> list[str]:
    """Effect names a module compares with or lists as literals (an effect's fact kept outside its module)."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
        elif isinstance(node, ast.Set | ast.List | ast.Tuple):
            operands = list(node.elts)
        elif isinstance(node, ast.Dict):
            operands = [k for k in node.keys if k is not None]
        else:
            continue
        found += [o.value for o in operands if isinstance(o, ast.Constant) and o.value in effects]
    return found


def test_the_diagnosis_names_no_effect():
    effects = frozenset(names())
    named = {p.name: hits for p in sorted(DIAGNOSE.glob("*.py"))
             if (hits := _named_effects(ast.parse(p.read_text()), effects))}
    assert named == {}
    assert _named_effects(ast.parse('STATIC = {"thermal": "temperature"}\nif c.effect == "offset_drift": pass'),
                          effects) == ["thermal", "offset_drift"]
