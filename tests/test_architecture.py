"""The layout promises of docs/architecture.md, checked on the source tree:
stage packages with a handful of modules at the top, no module over 400
lines, and no import cycle between modules (imports inside functions
included: a cycle deferred into a function is still a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

PIPELINE = Path(__file__).resolve().parents[1] / "pipeline" / "rotcal"
STAGES = {"ingest", "timebase", "segment", "fit", "combine", "metrology", "diagnose", "report", "batch", "simulate", "model"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PIPELINE).with_suffix("").parts
    return ".".join(("rotcal", *(parts[:-1] if parts[-1] == "__init__" else parts)))


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The rotcal modules a module imports (``from rotcal.x import y`` names
    module ``rotcal.x.y`` when that is a module, else ``rotcal.x``)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for alias in node.names:
                full = f"{node.module}.{alias.name}"
                found.add(full if full in modules else node.module)
    return found & modules


def import_graph() -> dict[str, set[str]]:
    files = {_module_name(p): p for p in PIPELINE.rglob("*.py")}
    return {name: _imports(path, set(files)) - {name} for name, path in files.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _package_parent(name: str) -> str:
    return name.rsplit(".", 1)[0]


def test_a_handful_of_modules_at_the_top_and_one_folder_per_stage():
    top = sorted(p.name for p in PIPELINE.glob("*.py"))
    assert len(top) <= 9, top  # the two front doors (cli, api) among them
    packages = {p.parent.name for p in PIPELINE.glob("*/__init__.py")}
    assert STAGES <= packages, STAGES - packages


def test_no_module_over_400_lines():
    long = {str(p.relative_to(PIPELINE)): n for p in PIPELINE.rglob("*.py") if (n := len(p.read_text().splitlines())) > 400}
    assert not long, long


def test_no_import_cycles():
    # a package's __init__ importing its own modules is how a package exposes
    # its stage functions, not a cycle between modules
    graph = import_graph()
    graph = {v: {w for w in ws if not (v == _package_parent(w) and w.startswith(v + "."))} for v, ws in graph.items()}
    assert cycles(graph) == []


def test_the_cycle_finder_finds_a_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
