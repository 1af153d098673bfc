"""The layout promises of docs/architecture.md, checked on the source tree:
stage packages with a handful of modules at the top, no module over 400
lines, no import cycle between modules and no import from a later stage
into an earlier one (imports inside functions and for type checking
included: a cycle deferred into a function is still a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

PIPELINE = Path(__file__).resolve().parents[1] / "pipeline" / "rotcal"
STAGES = {"ingest", "timebase", "segment", "fit", "combine", "metrology", "diagnose", "report", "batch", "simulate", "model",
          "noise", "blockwise"}


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


# The packages from the bottom up: each may import those before it, never one after it. The
# bottom holds what every stage reads (the version, errors, JSON text, cores, the configuration,
# the table contracts, the model); then the stages in the order a run calls them (ingest,
# time base, the noise model of the residuals, the segment fits' least-squares core, segmentation, the reductions, the diagnosis,
# metrology, the report), the block path (a single capture through those stages a block at a time), the run, and the commands built on it.
LAYERS = ("rotcal", "errors", "jsontext", "parallel", "config", "tables", "model",
          "ingest", "timebase", "noise", "fit", "segment", "combine", "diagnose", "metrology", "report",
          "blockwise", "run", "batch", "simulate", "apply", "cli", "api", "__main__")


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def backward_arrows(graph: dict[str, set[str]], layers: tuple[str, ...] = LAYERS) -> list[tuple[str, str]]:
    """(importer, imported) where the imported module's package comes later
    in ``layers`` than the importer's; a package ``layers`` does not place is
    an arrow from nowhere, ``("?", package)``, so that a new one gets its place."""
    rank = {name: k for k, name in enumerate(layers)}
    unplaced = sorted({("?", _layer(m)) for m in graph if _layer(m) not in rank})
    return unplaced + sorted((v, w) for v, ws in graph.items() for w in ws
                             if _layer(v) in rank and _layer(w) in rank and rank[_layer(w)] > rank[_layer(v)])


# the one arrow down by design: `import rotcal` offers the Python API (rotcal.api, the top layer) as
# rotcal.calibrate, ..., imported when first used (the package's __getattr__)
FRONT_DOOR = {("rotcal", "rotcal.api")}


def test_no_import_from_a_later_stage():
    assert [a for a in backward_arrows(import_graph()) if a not in FRONT_DOOR] == []


def test_the_direction_check_finds_a_backward_arrow():
    graph = {"rotcal.segment.x": {"rotcal.combine.y", "rotcal.fit.z"}, "rotcal.combine.y": {"rotcal.segment.x"},
             "rotcal.fit.z": set(), "rotcal.unplaced.w": set()}
    assert backward_arrows(graph) == [("?", "unplaced"), ("rotcal.segment.x", "rotcal.combine.y")]


RUN = PIPELINE / "run" / "__init__.py"
DRAWING = PIPELINE.parents[1] / "docs" / "architecture.md"


def run_sequence(source: str, function: str = "_run") -> list[str]:
    """The calls of ``function`` to functions imported from rotcal, as
    ``module.name`` (less ``rotcal.``), in the order they run: statements in
    order, a call's arguments before the call (a ``try``'s handlers after
    its body)."""
    tree = ast.parse(source)
    imported = {a.asname or a.name: f"{node.module.removeprefix('rotcal.')}.{a.name}"
                for node in tree.body if isinstance(node, ast.ImportFrom) and node.module
                and node.module.startswith("rotcal.") for a in node.names}
    body = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == function)
    calls: list[str] = []

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            visit(child)
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in imported:
            calls.append(imported[node.func.id])

    for statement in body.body:
        visit(statement)
    return calls


def drawn_sequence(text: str) -> list[str]:
    """The numbered calls of the drawing in docs/architecture.md: ``(1) blockwise.load.load``, ..."""
    import re

    steps = [(int(n), name) for n, name in re.findall(r"\((\d+)\) ([a-z_]+(?:\.[a-z_]+)+)", text)]
    assert [n for n, _ in steps] == list(range(1, len(steps) + 1)), steps
    return [name for _, name in steps]


def test_the_drawing_lists_the_runs_stage_calls_in_order():
    sequence = run_sequence(RUN.read_text())
    assert sequence[:4] == ["blockwise.load.load", "run.stages.segment_and_fit", "run.stages.reduce", "run.stages.determined"]
    assert drawn_sequence(DRAWING.read_text()) == sequence


def test_the_sequence_is_read_in_the_order_the_calls_run():
    source = ("from rotcal.a import f, g\nfrom rotcal.b.c import h as k\n"
              "def _run(x):\n    y = f(x)\n    try:\n        g(y)\n    except E:\n        k(1)\n    return f(g(y), k(2))\n")
    assert run_sequence(source) == ["a.f", "a.g", "b.c.h", "a.g", "b.c.h", "a.f"]
    assert drawn_sequence("x (1) run.a.b y\n (2) c.d") == ["run.a.b", "c.d"]


def test_no_history_in_the_package():
    """Docstrings and comments say what the code does and why; which issue
    asked for it lives in git."""
    import re

    cited = {str(p.relative_to(PIPELINE)): m.group(0) for p in PIPELINE.rglob("*.py")
             if (m := re.search(r"\bissues? \d+", p.read_text(), re.IGNORECASE))}
    assert cited == {}
