"""The package's structure: data flows one way (no module imports a layer above its own), and no import cycle.

Imports are read from the source with `ast`, function-local ones included, so a lazy import cannot hide an upward
dependency.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parent.parent / "symfunnel"

#: layers, lowest first; a module may import its own layer and the ones below
LAYERS = [
    ("ground", ["core", "expr", "sx", "family", "plant", "_callable"]),
    ("model", ["model"]),
    ("scenario", ["scenario"]),
    ("design", ["design"]),
    ("stages", ["simulate", "simulation", "codegen", "checks", "deployed"]),
    ("pipeline", ["pipeline", "campaigns", "synthesis"]),
    ("presentation", ["report", "bench", "commands", "cli", "__init__", "__main__", "api"]),
]


def _layer_of(module: str) -> int:
    top = module.split(".")[0]
    for i, (_, names) in enumerate(LAYERS):
        if top in names:
            return i
    raise AssertionError(f"module {module} is in no layer: add it to LAYERS")


def _modules() -> dict[str, Path]:
    out = {}
    for p in PKG.rglob("*.py"):
        rel = p.relative_to(PKG).with_suffix("")
        parts = list(rel.parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _imports(mod: str, path: Path) -> set[str]:
    """The symfunnel modules a module imports (absolute names without the package prefix)."""
    pkg_parts = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[:len(pkg_parts) - node.level + 1] if node.level > 1 else pkg_parts
                target = ".".join(base + ([node.module] if node.module else []))
                names = [target] if node.module else [".".join(base + [a.name]) for a in node.names]
            elif node.module and node.module.startswith("symfunnel"):
                names = [node.module[len("symfunnel."):] if node.module != "symfunnel" else "__init__"]
            else:
                continue
            out.update(n for n in names if n)
        elif isinstance(node, ast.Import):
            out.update(a.name[len("symfunnel."):] for a in node.names if a.name.startswith("symfunnel."))
    return out


def test_no_module_imports_a_layer_above_its_own():
    bad = []
    mods = _modules()
    for mod, path in mods.items():
        mine = _layer_of(mod)
        for dep in _imports(mod, path):
            if dep not in mods:
                continue                     # an attribute (from . import __version__), not a module
            if _layer_of(dep) > mine:
                bad.append(f"{mod} ({LAYERS[mine][0]}) imports {dep} ({LAYERS[_layer_of(dep)][0]})")
    assert not bad, "\n".join(bad)


def test_no_import_cycle_between_modules():
    mods = _modules()
    graph = {m: {d for d in _imports(m, p) if d in mods and d != m} for m, p in mods.items()}
    # a package's __init__ re-exporting its own submodules is not a cycle of the data flow
    for m in graph:
        graph[m] = {d for d in graph[m] if not (d.startswith(m + ".") or m.startswith(d + "."))}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in graph[m]:
            if state.get(d) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            if d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in graph:
        if m not in state:
            visit(m)


def test_the_checker_sees_a_lazy_upward_import(tmp_path):
    """The layer rule is not vacuous: a function-local import of the pipeline from the design layer is found."""
    p = tmp_path / "x.py"
    p.write_text("def f():\n    from ..pipeline import Run\n    return Run\n", encoding="utf-8")
    assert "pipeline" in _imports("design.x", p)
    assert _layer_of("pipeline") > _layer_of("design.x")


@pytest.mark.parametrize("registry, key", [("symfunnel.family.transforms:TRANSFORMS", "design.transform"),
                                           ("symfunnel.family.approximators:APPROXIMATORS", "approximator.type"),
                                           ("symfunnel.family.funnels:FUNNEL_SHAPES", "funnel.eK"),
                                           ("symfunnel.family.variants:VARIANTS", "design.variant")])
def test_each_registry_is_documented_in_the_scenario_docs(registry, key):
    import importlib
    mod, name = registry.split(":")
    reg = getattr(importlib.import_module(mod), name)
    assert reg.key == key
    docs = (PKG.parent / "docs" / "scenario.md").read_text(encoding="utf-8")
    for entry in reg:
        assert f"`{entry.name}`" in docs, (key, entry.name)
