"""The layers of the code base: no upward import and no import cycle (docs/architecture.md).

Every ``import`` / ``from ... import`` in ``slam/``, ``scenes/``, ``raytrace/``, ``pipelines/`` and
the top-level ``mmslam`` modules, at module level and inside functions (read from the AST; only
``if TYPE_CHECKING:`` blocks, which never run, are left out), must point to the same layer or a
lower one of :data:`LAYERS`, and the graph of these imports must have no cycle at all.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS: tuple[tuple[str, ...], ...] = (
    ("mmslam", "mmslam.errors", "mmslam.limits", "mmslam.model", "mmslam.outputs", "mmslam.backend",
     "mmslam.executor"),  # mmslam: __version__
    ("mmslam.scenes.params",),
    ("mmslam.scenes.meshes",),
    ("mmslam.scenes.geometry", "mmslam.scenes.driving"),
    ("mmslam.scenes.streets",),
    ("mmslam.scenes.scenario",),
    ("mmslam.scenes.trajectory", "mmslam.scenes.landmarks"),
    ("mmslam.scenes.plan", "mmslam.scenes.presets"),
    ("mmslam.scenes",),  # the package facade and the scenes CLI
    ("mmslam.raytrace",),
    ("mmslam.slam.core",),
    ("mmslam.slam.models",),
    ("mmslam.slam.phd", "mmslam.slam.fusion", "mmslam.slam.reference"),
    ("mmslam.slam.specs",),
    ("mmslam.slam.sim",),
    ("mmslam.slam.eval",),
    ("mmslam.slam.filter",),
    ("mmslam.slam",),  # the slam CLI
    ("mmslam.pipelines",),
    ("mmslam.cli", "mmslam.__main__"),
)
"""Lowest first; a module belongs to the layer of its longest matching prefix. A module may import
its own layer or any lower one; within a layer the import graph must still be acyclic."""

_RANK = {prefix: i for i, names in enumerate(LAYERS) for prefix in names}


def layer_of(module: str) -> int:
    parts = module.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in _RANK:
            return _RANK[".".join(parts[:n])]
    raise KeyError(module)


def modules(root: Path = ROOT) -> dict[str, Path]:
    """Module name -> source file of every module of the checked packages."""
    dirs = {"mmslam": root / "mmslam", "mmslam.scenes": root / "scenes", "mmslam.raytrace": root / "raytrace",
            "mmslam.slam": root / "slam", "mmslam.pipelines": root / "pipelines"}
    out = {}
    for pkg, d in dirs.items():
        for f in sorted(d.rglob("*.py")):
            rel = f.relative_to(d).with_suffix("").parts
            if pkg == "mmslam" and len(rel) > 1:
                continue
            name = ".".join((pkg,) + rel)
            out[name.removesuffix(".__init__")] = f
    return out


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for child in node.body:
                skip.update(id(n) for n in ast.walk(child))
    return skip


def imports_of(name: str, path: Path, known: set[str]) -> set[str]:
    """The checked modules ``name`` imports (module- and function-level, not under TYPE_CHECKING)."""
    tree = ast.parse(path.read_text(), str(path))
    skip = _type_checking_nodes(tree)
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    out = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                mod = ".".join(base[:len(base) - node.level + 1] + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            targets = [f"{mod}.{a.name}" if f"{mod}.{a.name}" in known else mod for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:  # a name inside a module: the module
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def import_graph(root: Path = ROOT) -> dict[str, set[str]]:
    mods = modules(root)
    known = set(mods)
    return {name: imports_of(name, path, known) for name, path in mods.items()}


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for a, targets in graph.items():
        for b in targets:
            if layer_of(b) > layer_of(a):
                bad.append(f"{a} imports {b} (layer {layer_of(b)} above {layer_of(a)})")
    return sorted(bad)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on, out = {}, {}, [], set(), []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_every_module_has_a_layer():
    missing = [m for m in modules() if not any(m == p or m.startswith(p + ".") for p in _RANK)]
    assert not missing, f"modules without a layer in LAYERS: {missing}"


def test_no_upward_import():
    bad = upward_imports(import_graph())
    assert not bad, "upward imports:\n" + "\n".join(bad)


def test_no_import_cycle():
    cyc = cycles(import_graph())
    assert not cyc, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cyc)


def test_slam_modules_stay_small():
    big = {str(p.relative_to(ROOT)): n for p in (ROOT / "slam").rglob("*.py")
           if (n := len(p.read_text().splitlines())) > 500}
    assert not big, f"slam/ modules over 500 lines: {big}"


def test_the_checker_sees_function_level_imports_and_cycles(tmp_path):
    """The checker itself: a function-level upward import and a two-module cycle are found; a
    TYPE_CHECKING import is not."""
    for pkg in ("mmslam", "scenes", "raytrace", "pipelines", "slam/core", "slam/phd"):
        (tmp_path / pkg).mkdir(parents=True)
    (tmp_path / "slam" / "core" / "a.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ..phd import b\n"
        "def f():\n    from ..phd.b import g\n    return g\n")
    (tmp_path / "slam" / "phd" / "b.py").write_text("from ..core import a\ndef g():\n    pass\n")
    (tmp_path / "slam" / "phd" / "c.py").write_text("def h():\n    from mmslam.slam.phd.d import x\n")
    (tmp_path / "slam" / "phd" / "d.py").write_text("from . import c\nx = 1\n")
    graph = import_graph(tmp_path)
    assert graph["mmslam.slam.core.a"] == {"mmslam.slam.phd.b"}
    assert upward_imports(graph) == ["mmslam.slam.core.a imports mmslam.slam.phd.b (layer 12 above 10)"]
    assert sorted(cycles(graph)) == [["mmslam.slam.core.a", "mmslam.slam.phd.b"],
                                     ["mmslam.slam.phd.c", "mmslam.slam.phd.d"]]


@pytest.mark.parametrize("module", ["mmslam.slam", "mmslam.slam.filter", "mmslam.slam.specs.landmarks"])
def test_slam_never_imports_sionna(module):
    import subprocess
    import sys

    code = (f"import sys, {module}; bad = [m for m in sys.modules if m.split('.')[0] in "
            "('sionna', 'mitsuba', 'drjit')]; assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)
