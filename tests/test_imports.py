"""The package's import graph: no circles, no upward imports, no private names across modules.

Every module of the four packages is parsed with ``ast`` (nothing is imported), and every
``import`` / ``from ... import`` statement anywhere in it (function-level imports too) is an edge
to the deepest module of the project it names. Imports under ``if TYPE_CHECKING:`` are left out:
they never run, so they can neither close a circle nor load a layer.

The layers (docs/architecture.md draws them): a package or ``simulate`` unit may import only the
ones listed below it in ``TOP_LEVEL`` / ``SIMULATE_LAYERS`` (a unit imports units of strictly lower
layers, plus its own modules).
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("data_manifest", "simulate", "learn", "pipelines")

#: What each top-level package may import of the others.
TOP_LEVEL = {
    "data_manifest": set(),
    "simulate": set(),
    "learn": {"data_manifest", "simulate"},
    "pipelines": {"data_manifest", "simulate", "learn"},
}

#: Units of ``simulate`` from the bottom up; a unit imports only units of lower layers.
SIMULATE_LAYERS = (
    ("simulate",),  # the package's __init__ (Warp's log level)
    ("simulate.cloth",),  # model, state, control, builder, fabrics
    ("simulate.contact",),  # body collider, self-contact
    ("simulate.solvers", "simulate.quality"),  # time steppers; frame measurements
    ("simulate.quasi_static", "simulate.body"),  # frame driver with per-world status; body models
    ("simulate.poses", "simulate.motion", "simulate.scenes"),  # pose sampling and interpolation; motion
    #                                                          trajectories; test and benchmark scenes
    ("simulate.garment",),  # templates, styles, canonical drapes
    ("simulate.sequence",),  # the sequence driver
    ("simulate.reports", "simulate.viz"),  # accuracy / stability reports, renders
)


def _module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    """{dotted module name: file} of every module of the four packages."""
    return {_module_name(f): f for pkg in PACKAGES for f in sorted((ROOT / pkg).rglob("*.py"))}


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """ids of the statements under ``if TYPE_CHECKING:`` blocks."""
    skip = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If):
            test = node.test
            name = test.id if isinstance(test, ast.Name) else test.attr if isinstance(test, ast.Attribute) else None
            if name == "TYPE_CHECKING":
                for stmt in node.body:
                    skip.update(id(n) for n in ast.walk(stmt))
    return skip


def import_graph(modules: dict[str, Path]):
    """(edges {module: {imported project module}}, private [(module, imported module, name)]).

    ``from a.b import c`` is an edge to ``a.b.c`` when that is a module, else to ``a.b``; a name that
    does not resolve to a module of the project (third-party) is no edge."""

    def resolve(name: str) -> str | None:
        while name and name not in modules:
            name = name.rpartition(".")[0]
        return name or None

    edges: dict[str, set[str]] = {m: set() for m in modules}
    private = []
    for mod, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        skip = _type_checking_nodes(tree)
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(tree):
            if id(node) in skip:
                continue
            if isinstance(node, ast.Import):
                for alias in node.names:
                    target = resolve(alias.name)
                    if target:
                        edges[mod].add(target)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                for alias in node.names:
                    full = f"{base}.{alias.name}"
                    target = full if full in modules else resolve(base)
                    if not target:
                        continue
                    edges[mod].add(target)
                    if alias.name.startswith("_") and not alias.name.startswith("__") and target != mod:
                        private.append((mod, target, alias.name))
        edges[mod].discard(mod)
    return edges, private


def find_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, on_stack, stack, out = {}, {}, set(), [], []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
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

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def _simulate_layer(mod: str) -> tuple[int, str] | None:
    """(layer, unit) of a ``simulate`` module: its longest listed unit prefix (the package
    ``simulate`` itself is the unit of its ``__init__`` only)."""
    best = None
    for layer, units in enumerate(SIMULATE_LAYERS):
        for unit in units:
            if (mod == unit or (mod.startswith(unit + ".") and unit != "simulate")) and (best is None or len(unit) > len(best[1])):
                best = (layer, unit)
    return best


def upward_imports(edges: dict[str, set[str]]) -> list[str]:
    bad = []
    for mod, targets in edges.items():
        top = mod.split(".")[0]
        for target in targets:
            other = target.split(".")[0]
            if other != top:
                if other not in TOP_LEVEL[top]:
                    bad.append(f"{mod} -> {target} ({top} may import only {sorted(TOP_LEVEL[top]) or 'none of the others'})")
                continue
            if top != "simulate":
                continue
            src, dst = _simulate_layer(mod), _simulate_layer(target)
            if src is None or dst is None:
                bad.append(f"{mod} -> {target}: {mod if src is None else target} is in no layer of SIMULATE_LAYERS")
            elif src[1] != dst[1] and dst[0] >= src[0]:
                bad.append(f"{mod} -> {target} ({dst[1]} is not below {src[1]})")
    return sorted(bad)


def test_graph_parser_sees_every_kind_of_import(tmp_path):
    """The checks are only as good as the graph: relative, function-level and ``from pkg import
    module`` imports are edges, third-party names and TYPE_CHECKING imports are not."""
    modules = project_modules()
    edges, private = import_graph(modules)
    assert len(modules) > 50
    # function-level import (pipelines.generate_dataset imports the sequence driver inside a function)
    assert any(t.startswith("simulate.sequence") for t in edges["pipelines.generate_dataset"])
    # relative import: data_manifest.validate uses ``from .manifest import ...``
    assert "data_manifest.manifest" in edges["data_manifest.validate"]
    # ``from simulate.solvers import common_kernels`` is an edge to the module, not the package
    assert "simulate.solvers.common_kernels" in edges["simulate.solvers.base"]
    assert not any(t.split(".")[0] in ("numpy", "warp", "torch") for ts in edges.values() for t in ts)
    # a made-up graph with a circle, an upward edge and a private name
    pkg = tmp_path / "simulate"
    (pkg / "cloth").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "cloth" / "__init__.py").write_text("")
    (pkg / "cloth" / "model.py").write_text("def f():\n    from simulate.sequence import _loop\n")
    (pkg / "sequence.py").write_text("from typing import TYPE_CHECKING\nfrom simulate.cloth import model\n"
                                     "if TYPE_CHECKING:\n    from simulate.reports import x\n")
    fake = {"simulate": pkg / "__init__.py", "simulate.cloth": pkg / "cloth" / "__init__.py",
            "simulate.cloth.model": pkg / "cloth" / "model.py", "simulate.sequence": pkg / "sequence.py",
            "simulate.reports": pkg / "sequence.py"}
    e, p = import_graph(fake)
    assert e["simulate.sequence"] == {"simulate.cloth.model"}  # the TYPE_CHECKING import is no edge
    assert find_cycles(e) == [["simulate.cloth.model", "simulate.sequence"]]
    assert upward_imports(e) == ["simulate.cloth.model -> simulate.sequence (simulate.sequence is not below simulate.cloth)"]
    assert p == [("simulate.cloth.model", "simulate.sequence", "_loop")]


def test_no_import_circles():
    cycles = find_cycles(import_graph(project_modules())[0])
    assert not cycles, "modules that import each other (directly or around a circle):\n" + "\n".join(
        " <-> ".join(c) for c in cycles)


def test_no_upward_imports():
    bad = upward_imports(import_graph(project_modules())[0])
    assert not bad, "imports against the layering (see the module docstring):\n" + "\n".join(bad)


def test_no_private_names_across_modules():
    private = import_graph(project_modules())[1]
    assert not private, "private names imported from another module:\n" + "\n".join(
        f"{m} takes {name} from {t}" for m, t, name in private)
