"""The package's imports point one way (STYLE.md "Layers"): no cycle, no upward arrow.

The checker parses every module of ``jaxslam`` with ``ast`` (module-level and function-local
imports alike: a lazy import is still a dependency), resolves relative imports, and drops the
edge from a module to its own ancestor packages (``from . import x`` inside a package touches
the package's ``__init__`` by construction).  Layers, lowest first:

0 infrastructure  errors, runtime, compilation, linalg, stats, files, the package root
1 models          geometry, dynamics, sensors, features, metrics, data (loaders, events, catalogue)
2 generic         filters, control
3 systems         systems
4 applications    sim, tuning, plotting, cli, data.runners, data.presets, io, paramfile, progress,
                  __main__

A module may import its own layer or any lower one; ``filters`` never imports ``metrics``,
``systems``, ``data``, ``sim``, ``tuning``, ``plotting`` or ``cli`` (generic algorithms name no
paper and no dataset).  The same checker is shown failing on a package with a deliberate cycle
and on one with an upward import.
"""

from __future__ import annotations

import ast
import pathlib

import pytest

PKG = pathlib.Path(__file__).resolve().parents[1] / "jaxslam"

LAYER_OF = {
    "errors": 0, "runtime": 0, "compilation": 0, "linalg": 0, "stats": 0, "files": 0,
    "geometry": 1, "dynamics": 1, "sensors": 1, "features": 1, "metrics": 1, "data": 1,
    "filters": 2, "control": 2,
    "systems": 3,
    "sim": 4, "tuning": 4, "plotting": 4, "cli": 4, "io": 4, "paramfile": 4, "progress": 4,
    "__main__": 4,
}
APP_MODULES = {"data.runners": 4, "data.presets": 4}  # application modules inside a models-level package
FILTERS_NEVER = ("metrics", "systems", "data", "sim", "tuning", "plotting", "cli")


def modules(root: pathlib.Path) -> dict:
    """{dotted name: path} of every module under the package folder ``root``."""
    out = {}
    for p in root.rglob("*.py"):
        parts = (root.name,) + p.relative_to(root).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = p
    return out


def edges(root: pathlib.Path) -> dict:
    """{module: set of package modules it imports} (ancestor packages left out)."""
    mods = modules(root)

    def known(name):
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    out = {}
    for m, path in mods.items():
        pkg = m if path.name == "__init__.py" else m.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg.split(".")[: len(pkg.split(".")) - (node.level - 1)]
                    mod = ".".join(base + ([node.module] if node.module else []))
                else:
                    mod = node.module or ""
                names = [mod] + [f"{mod}.{a.name}" for a in node.names]
            else:
                continue
            for n in names:
                t = known(n) if n.split(".")[0] == root.name else None
                if t and t != m and not m.startswith(t + "."):
                    targets.add(t)
        out[m] = targets
    return out


def cycles(graph: dict) -> list:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v):
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
                found.append(sorted(comp))

    for v in list(graph):
        if v not in index:
            visit(v)
    return found


def layer(module: str, layer_of=LAYER_OF, apps=APP_MODULES):
    rest = module.split(".", 1)[1] if "." in module else ""
    for name, lv in apps.items():
        if rest == name or rest.startswith(name + "."):
            return lv
    return layer_of.get(rest.split(".")[0], 0) if rest else 0


def violations(graph: dict, layer_of=LAYER_OF, apps=APP_MODULES) -> list:
    """Upward imports and the generic algorithms' forbidden imports, as readable lines."""
    bad = []
    for m, targets in sorted(graph.items()):
        for t in sorted(targets):
            if layer(t, layer_of, apps) > layer(m, layer_of, apps):
                bad.append(f"{m} (layer {layer(m, layer_of, apps)}) imports {t} (layer {layer(t, layer_of, apps)})")
            top_m = m.split(".")[1] if "." in m else ""
            top_t = t.split(".")[1] if "." in t else ""
            if top_m == "filters" and top_t in FILTERS_NEVER:
                bad.append(f"{m} imports {t}: generic filters never import {top_t}")
    return bad


def test_every_top_level_part_has_a_layer():
    tops = {p.stem if p.suffix == ".py" else p.name for p in PKG.iterdir()
            if (p.suffix == ".py" and p.stem != "__init__") or (p.is_dir() and (p / "__init__.py").exists())}
    assert tops <= set(LAYER_OF), sorted(tops - set(LAYER_OF))


def test_package_imports_are_acyclic_and_point_down():
    graph = edges(PKG)
    assert len(graph) > 80 and sum(len(t) for t in graph.values()) > 150  # the checker sees the package
    assert cycles(graph) == []
    assert violations(graph) == []


def _fake(tmp_path, files: dict) -> pathlib.Path:
    root = tmp_path / "jaxslam"
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return root


@pytest.mark.parametrize("files, kind", [
    ({"__init__.py": "", "filters/__init__.py": "", "filters/a.py": "from . import b\n",
      "filters/b.py": "def f():\n    from .a import g\n"}, "cycle"),
    ({"__init__.py": "", "filters/__init__.py": "", "systems/__init__.py": "",
      "filters/a.py": "from ..systems import paper\n", "systems/paper.py": "from ..filters import a\n"}, "cycle"),
    ({"__init__.py": "", "filters/__init__.py": "", "systems/__init__.py": "",
      "filters/a.py": "import jaxslam.systems.paper\n", "systems/paper.py": "x = 1\n"}, "upward"),
    ({"__init__.py": "", "filters/__init__.py": "", "metrics.py": "",
      "filters/a.py": "from jaxslam.metrics import ate\n"}, "filters"),
])
def test_the_checker_fails_on_a_deliberate_cycle_or_upward_import(tmp_path, files, kind):
    graph = edges(_fake(tmp_path, files))
    if kind == "cycle":
        assert cycles(graph), graph
    else:
        bad = violations(graph)
        assert bad and (kind != "filters" or "never import metrics" in bad[-1]), bad
