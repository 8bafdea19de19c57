"""The project's own modules import each other without cycles, and only downwards (issue 15).

Every import counts, including those inside functions (144 of 317 were, hiding three cycles) and those in
``if TYPE_CHECKING:`` blocks: they never run, but a module that names a type of a module above it still
depends on it (it cannot be understood, type-checked or moved without it). A cycle means two modules
cannot be understood, tested or moved apart; the fix is to move what both need into a module below both.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "meshprep")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = p.relative_to(ROOT).with_suffix("").parts
            out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return out


def graph_of(sources: dict[str, str]) -> dict[str, set[str]]:
    """module -> the modules of ``sources`` (module name -> source text) it imports.

    ``from a.b import c`` counts a.b.c when it is a module, else a.b; an import counts wherever it is (module
    level, in a function, under ``if TYPE_CHECKING:``).
    """
    def resolve(name: str) -> str | None:
        while name and name not in sources:
            name = name.rpartition(".")[0]
        return name or None

    graph: dict[str, set[str]] = {m: set() for m in sources}
    for m, text in sources.items():
        for node in ast.walk(ast.parse(text)):
            targets = []
            if isinstance(node, ast.Import):
                targets = [resolve(a.name) for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets = [resolve(f"{node.module}.{a.name}") for a in node.names]
            graph[m] |= {t for t in targets if t and t != m}
    return graph


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports (:func:`graph_of` of the packages' files)."""
    return graph_of({m: p.read_text(encoding="utf-8") for m, p in _modules().items()})


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan's algorithm, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    x = stack.pop()
                    on.discard(x)
                    comp.append(x)
                    if x == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_cycles():
    found = cycles(import_graph())
    assert found == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_the_cycle_finder_finds_cycles():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_function_level_imports_are_seen():
    """The graph sees an import inside a function (the three cycles the issue found hid there)."""
    g = import_graph()
    assert "pipeline.synthscan" in g["pipeline.cli"]             # `from pipeline.synthscan import ...` in a function
    assert "pipeline.seeding" in g["pipeline.stages"]            # in StageContext.rng


# two modules of a planted package: ``low`` names a type of ``high`` for the type checker only
TYPE_CHECKING_CYCLE = {
    "pkg.high": "from pkg.low import helper\n",
    "pkg.low": ("from __future__ import annotations\n"
                "import typing\n"
                "from typing import TYPE_CHECKING\n"
                "if TYPE_CHECKING:\n"
                "    from pkg.high import Thing\n"
                "if typing.TYPE_CHECKING:\n"
                "    import pkg.high\n"
                "def helper(t: Thing) -> None:\n"
                "    pass\n"),
}


def test_type_checking_imports_count():
    """An import under ``if TYPE_CHECKING:`` (either spelling) is an edge: it closes a cycle, and pointing up
    the layers it is an upward import."""
    g = graph_of(TYPE_CHECKING_CYCLE)
    assert g == {"pkg.high": {"pkg.low"}, "pkg.low": {"pkg.high"}}
    assert cycles(g) == [["pkg.high", "pkg.low"]]
    up = graph_of({"pipeline.types": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                     "    from pipeline.raster import RasterFrame\n",
                   "pipeline.raster": ""})
    assert upward_imports(up) == ["pipeline.types (base) imports pipeline.raster (stages)"]


def test_meshprep_imports_nothing_from_pipeline():
    g = import_graph()
    assert not [m for m, deps in g.items() if m.startswith("meshprep") and any(d.startswith("pipeline") for d in deps)]


# The layers, lowest first (README, "Development"): a module imports only from its own layer or lower
# ones, and a stage never imports another stage (it reads their files through pipeline.runfolder).
BASE = {"pipeline", "pipeline.errors", "pipeline.tolerances", "pipeline.seeding", "pipeline.presets",
        "pipeline.config", "pipeline.stages", "pipeline.camera", "pipeline.color", "pipeline.geometry",
        "pipeline.types", "pipeline.io", "pipeline.gl", "pipeline.threads"}
RUN_FOLDER = {"pipeline.runfolder", "pipeline.runner"}
STAGES = {"pipeline.ingest", "pipeline.select", "pipeline.prep", "pipeline.simulate", "pipeline.raster",
          "pipeline.trace.stage", "pipeline.composite", "pipeline.export"}
APP = {"pipeline.cli", "pipeline.__main__", "pipeline.report", "pipeline.report_html", "pipeline.report_cli",
       "pipeline.preview_cli", "pipeline.docs"}
LAYER_NAMES = ("meshprep", "base", "libraries", "run folder", "stages", "application")


def layer(module: str) -> int:
    if module.startswith("meshprep"):
        return 0
    for k, group in enumerate((BASE, None, RUN_FOLDER, STAGES, APP), start=1):
        if group is not None and module in group:
            return k
    return 2   # every other pipeline module: a library (geometry, physics, tracer, formats, synthscan...)


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    out = []
    for m, deps in sorted(graph.items()):
        for d in sorted(deps):
            if layer(d) > layer(m) or (m in STAGES and d in STAGES and d != m):
                out.append(f"{m} ({LAYER_NAMES[layer(m)]}) imports {d} ({LAYER_NAMES[layer(d)]})")
    return out


def test_imports_only_go_down_the_layers():
    assert upward_imports(import_graph()) == []


def test_the_layer_check_finds_an_upward_import():
    assert upward_imports({"pipeline.types": {"pipeline.raster"}}) == \
        ["pipeline.types (base) imports pipeline.raster (stages)"]
    assert upward_imports({"pipeline.composite": {"pipeline.raster"}}) == \
        ["pipeline.composite (stages) imports pipeline.raster (stages)"]
    assert upward_imports({"pipeline.raster": {"pipeline.runfolder", "pipeline.annotate"}}) == []


# The product's tests and code stand without the benchmarks: ``bench/`` is dev-only and imports from the
# tests' shared references (``tests.support``), never the other way. Only the tests of the bench scripts
# themselves (``tests/bench/``) import ``bench``; nothing in the packages imports ``bench`` or ``tests``.
def foreign_imports(sources: dict[str, str], forbidden: tuple[str, ...]) -> list[str]:
    """``"<module> imports <name>"`` for each import in ``sources`` (module name -> source text) of a
    package in ``forbidden`` or one of its modules, wherever the import is."""
    out = []
    for m, text in sorted(sources.items()):
        for node in ast.walk(ast.parse(text)):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            out += [f"{m} imports {n}" for n in names if n.split(".")[0] in forbidden]
    return out


def _test_sources() -> dict[str, str]:
    tests = ROOT / "tests"
    return {".".join(p.relative_to(ROOT).with_suffix("").parts): p.read_text(encoding="utf-8")
            for p in sorted(tests.rglob("*.py")) if not p.is_relative_to(tests / "bench")}


def test_product_tests_import_nothing_from_bench():
    assert foreign_imports(_test_sources(), ("bench",)) == []


def test_the_packages_import_nothing_from_bench_or_tests():
    sources = {m: p.read_text(encoding="utf-8") for m, p in _modules().items()}
    assert foreign_imports(sources, ("bench", "tests")) == []


def test_the_bench_check_finds_a_bench_import():
    planted = {"tests.pipeline.test_a": "def test():\n    from bench.reference import raycast\n",
               "tests.pipeline.test_b": "import bench\nimport benchmark\nfrom tests.support.reference import iou\n",
               "tests.pipeline.test_c": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import bench.common\n"}
    assert foreign_imports(planted, ("bench",)) == ["tests.pipeline.test_a imports bench.reference",
                                                    "tests.pipeline.test_b imports bench",
                                                    "tests.pipeline.test_c imports bench.common"]
