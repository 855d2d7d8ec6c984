"""The package's import graph: no circles, and imports that only run downhill (docs/architecture.md).

Every module under ``src/pavemap`` is parsed with :mod:`ast` (nothing is imported, so the check is fast and
sees what a run would not: imports inside functions and under ``if TYPE_CHECKING:`` count like any other).
A function-level import still ties the two modules together (it runs, just later), so a circle hidden in a
function is a circle. A ``TYPE_CHECKING`` import never runs, but the annotation it serves still makes the
lower module know the upper one's type, which is the coupling the layers forbid; so it counts too.

Importing ``pavemap.a.b`` also runs ``pavemap/a/__init__.py``; that implicit parent import is not an edge
(every module would then depend on every package face above it), only the module a statement names is.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: The layers from the ground up: a module may import its own layer and the layers below it, never above.
#: A module belongs to the longest prefix listed here. Modules in one layer may import each other (no circles).
LAYERS: tuple[tuple[str, ...], ...] = (
    # 0 ground: plain data types, errors, colours, the version, the device, cache and memory helpers, typed values
    ("pavemap.types", "pavemap.errors", "pavemap.palette", "pavemap.version", "pavemap.device",
     "pavemap.shutdown", "pavemap.user_cache", "pavemap.assets", "pavemap.weights", "pavemap.typed_values",
     "pavemap.memory"),
    ("pavemap.geometry",),  # 1 cameras, rays, grids, height fields, patch matching: numbers in, numbers out
    ("pavemap.io",),  # 2 the sequence folder and the files pavemap reads and writes; the importers of real data
    ("pavemap.geo",),  # 3 georeferencing: GPS fits, local tangent plane, CRS, coverage
    ("pavemap.mesh",),  # 4 stage 1: the differentiable road mesh and its ground points
    ("pavemap.sfm",),  # 5 camera poses from plain video (uses the mesh's ground points for the metric scale)
    ("pavemap.detect",),  # 6 stage 2: detections and the semantic filter
    ("pavemap.segment",),  # 7 per-frame semantic masks (the YOLO segmenter reuses the detector's loader)
    ("pavemap.ingest",),  # 7b importers of own drives and KITTI: files + poses (given or SfM) + geo -> sequence
    ("pavemap.fuse",),  # 8 stage 3: multi-frame fusion into defect instances
    ("pavemap.maintain",),  # 9 measures and repair priorities of fused defects
    ("pavemap.export",),  # 10 GeoJSON, GeoTIFF, GIS, CSV, the HTML report
    ("pavemap.evaluate", "pavemap.synth"),  # 11 scoring against truth; the synthetic world (writes truth files)
    # 12 run config, run folder, survey change, the checks before a run's first long stage
    ("pavemap.config", "pavemap.run_folder", "pavemap.compare", "pavemap.preflight"),
    ("pavemap.pipeline",),  # 13 one sequence end to end
    ("pavemap.network",),  # 14 many drives: batch, register, network report
    # 15 the CLI, the package's lazy face, and the weights command's checks (they load through detect / segment)
    ("pavemap.commands", "pavemap.cli", "pavemap", "pavemap.weights.manage"),
)

#: Imports that run up a layer on purpose, each (importer, imported) with why. Keep this short (issue 44: <= 3).
ALLOWED_UPWARD: dict[tuple[str, str], str] = {}


def _modules() -> dict[str, tuple[Path, bool]]:
    """{dotted name: (file, is a package's __init__)} for every module under src/pavemap."""
    out = {}
    for p in sorted((SRC / "pavemap").rglob("*.py")):
        parts = list(p.relative_to(SRC).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (p, is_pkg)
    return out


def _targets(mod: str, is_pkg: bool, node: ast.Import | ast.ImportFrom, mods: dict) -> list[str]:
    """The pavemap modules one import statement names (``from pkg import sub`` names the module ``pkg.sub``)."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:  # relative: resolve against this module's package
            base = mod.split(".") if is_pkg else mod.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            prefix = ".".join(base + ([node.module] if node.module else []))
        else:
            prefix = node.module or ""
        names = [f"{prefix}.{a.name}" if f"{prefix}.{a.name}" in mods else prefix for a in node.names]
    out = []
    for name in names:
        while name not in mods and "." in name:  # `import pavemap.a.b.func` -> the module that holds it
            name = name.rsplit(".", 1)[0]
        if name in mods and name != mod:
            out.append(name)
    return out


def import_graph() -> dict[str, set[str]]:
    """{module: the pavemap modules it imports anywhere in its source}."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, (path, is_pkg) in mods.items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import | ast.ImportFrom):
                graph[mod].update(_targets(mod, is_pkg, node, mods))
    return graph


def layer_of(mod: str) -> int:
    best, layer = -1, -1
    for i, prefixes in enumerate(LAYERS):
        for p in prefixes:
            if (mod == p or mod.startswith(p + ".")) and len(p) > best:
                best, layer = len(p), i
    return layer


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return sorted(out)


def upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    return sorted((a, b) for a, bs in graph.items() for b in bs if layer_of(b) > layer_of(a))


def test_every_module_has_a_layer() -> None:
    assert [m for m in import_graph() if layer_of(m) < 0] == []


def test_no_import_circles() -> None:
    found = circles(import_graph())
    assert found == [], "import circles:\n" + "\n".join(" <-> ".join(c) for c in found)


def test_imports_run_downhill() -> None:
    ups = [e for e in upward_imports(import_graph()) if e not in ALLOWED_UPWARD]
    lines = [f"{a} (layer {layer_of(a)}) imports {b} (layer {layer_of(b)})" for a, b in ups]
    assert ups == [], "upward imports not on the allow-list:\n" + "\n".join(lines)


def test_allow_list_is_short_and_live() -> None:
    """An allowed upward import that is gone must leave the list (so the list never hides a new one)."""
    assert len(ALLOWED_UPWARD) <= 3
    graph = import_graph()
    assert [e for e in ALLOWED_UPWARD if e[1] not in graph.get(e[0], set())] == []


@pytest.mark.parametrize(("source", "expect"), [
    ("from pavemap.b import f\n", {"pavemap.b"}),
    ("def f():\n    from pavemap.b import g\n", {"pavemap.b"}),  # hidden in a function: still an edge
    ("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pavemap.b import T\n", {"pavemap.b"}),
    ("from . import b\n", {"pavemap.b"}),
    ("import pavemap.b\n", {"pavemap.b"}),
])
def test_graph_reader_sees_each_kind_of_import(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                               source: str, expect: set[str]) -> None:
    """The checker itself can fail: a tiny package whose a <-> b circle is written each way."""
    pkg = tmp_path / "pavemap"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text(source)
    (pkg / "b.py").write_text("from pavemap.a import x\n")
    monkeypatch.setitem(globals(), "SRC", tmp_path)
    graph = import_graph()
    assert graph["pavemap.a"] == expect
    assert circles(graph) == [["pavemap.a", "pavemap.b"]]
