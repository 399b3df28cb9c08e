"""The package's structure is its architecture: the layer of a module is the package it is in, data flows one way
(no module imports a package above its own), and no import cycle, function-local and `importlib` imports included.

The checker reads imports from the source with `ast`, so a lazy import cannot hide a dependency; it is tested on
synthetic packages with a deliberate upward import and a deliberate cycle. `docs/architecture.md`'s module map is
generated from the packages' docstrings (`python -m tests.test_architecture --write` rewrites it).
"""

from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parent.parent / "symfunnel"
DOC = PKG.parent / "docs" / "architecture.md"

#: the layers, lowest first: each is a package of symfunnel (or one of the few top-level modules); a module may
#: import modules of its own layer and of the layers below
LAYERS = ("core", "sx", "expr", "family", "model", "plant", "scenario", "design", "simulation", "emit", "deployed",
          "checks", "certificates", "pipeline", "campaigns", "synthesis", "reporting", "api", "bench", "commands",
          "cli", "__main__", "__init__")

#: the only modules allowed at the package's top level
TOP_LEVEL = {"__init__", "__main__", "api", "cli", "pipeline"}


def modules(root: Path) -> dict[str, Path]:
    """Dotted module name (without the package prefix; a package's __init__ is the package) -> file."""
    out = {}
    for p in sorted(root.rglob("*.py")):
        parts = list(p.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__" and len(parts) > 1:
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def _const_prefix(node: ast.AST) -> tuple[str, bool] | None:
    """(text, complete) of a string argument: a constant, or the constant start of an f-string / a + b."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value, True
    if isinstance(node, ast.JoinedStr):
        head = ""
        for v in node.values:
            if isinstance(v, ast.Constant):
                head += v.value
            else:
                return head, False
        return head, True
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        left = _const_prefix(node.left)
        if left and left[1]:
            right = _const_prefix(node.right)
            return (left[0] + right[0], right[1]) if right else (left[0], False)
        return left
    return None


def imports(mod: str, path: Path, root_name: str = "symfunnel") -> set[str]:
    """Every module of the package that `mod` imports: import statements anywhere (function-local too), and
    `importlib.import_module` / `__import__` calls; a call whose name is computed counts as importing every
    module under its constant prefix, and one with no resolvable prefix imports everything ('*'). A name
    `from T import N` is given as 'T:N' (the submodule T.N if there is one, else T; see `_resolve`)."""
    pkg_parts = mod.split(".") if path.name == "__init__.py" else mod.split(".")[:-1]
    if mod == "__init__":
        pkg_parts = []
    prefix = root_name + "."
    out: set[str] = set()

    def absolute(name: str) -> str | None:
        if name == root_name:
            return "__init__"
        return name[len(prefix):] if name.startswith(prefix) else None

    def relative(level: int, name: str) -> str:
        base = pkg_parts[:len(pkg_parts) - level + 1] if level > 1 else pkg_parts
        return ".".join(base + ([name] if name else [])) or "__init__"

    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                target = relative(node.level, node.module or "")
            elif node.module and absolute(node.module) is not None:
                target = absolute(node.module)
            else:
                continue
            out.update(f"{target}:{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a for a in (absolute(x.name) for x in node.names) if a)
        elif isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
            if name not in ("import_module", "__import__") or not node.args:
                continue
            arg = _const_prefix(node.args[0])
            if arg is None:
                out.add("*")
                continue
            text, complete = arg
            if text.startswith("."):                     # import_module(".x", __name__): relative to the package
                level = len(text) - len(text.lstrip("."))
                target = relative(level, text.lstrip(".").rstrip("."))
            elif absolute(text.rstrip(".")) is not None:
                target = absolute(text.rstrip("."))
            elif text in ("", root_name + ".") or text.startswith(prefix[:len(text)]) and not complete:
                out.add("*")
                continue
            else:
                continue
            out.add(target if complete else target + ".*")
    return out


def _resolve(dep: str, mods: dict[str, Path]) -> set[str]:
    """The modules an import name stands for: itself (or its package), or every module under a 'pkg.*'."""
    if dep == "*":
        return set(mods)
    if ":" in dep:                               # from TARGET import NAME: the submodule NAME, else TARGET itself
        target, name = dep.split(":")
        sub = name if target == "__init__" else f"{target}.{name}"
        dep = sub if sub in mods else target
    if dep.endswith(".*"):
        base = dep[:-2]
        return {m for m in mods if m == base or m.startswith(base + ".")} if base != "__init__" else set(mods)
    while dep and dep not in mods:
        dep = dep.rpartition(".")[0]
    return {dep} if dep else set()


def graph(root: Path) -> dict[str, set[str]]:
    """module -> modules it imports (itself excluded)."""
    mods = modules(root)
    return {m: {d for dep in imports(m, p, root.name) for d in _resolve(dep, mods)} - {m} for m, p in mods.items()}


def layer_of(module: str, layers=LAYERS) -> int:
    """Index of a module's layer: the top-level package (or top-level module) it belongs to."""
    top = module.split(".")[0]
    if top not in layers:
        raise AssertionError(f"{module} is in no layer: put its package into LAYERS")
    return layers.index(top)


def upward_imports(root: Path, layers=LAYERS) -> list[str]:
    """Every import of a module from a layer above its own."""
    bad = []
    for mod, deps in graph(root).items():
        for dep in sorted(deps):
            if layer_of(dep, layers) > layer_of(mod, layers):
                bad.append(f"{mod} ({layers[layer_of(mod, layers)]}) imports {dep} "
                           f"({layers[layer_of(dep, layers)]})")
    return bad


def cycles(root: Path) -> list[list[str]]:
    """One import cycle per strongly connected component of more than one module (Tarjan)."""
    g = graph(root)
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]
    sys.setrecursionlimit(max(10000, sys.getrecursionlimit()))

    def strong(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(g[v]):
            if w not in index:
                strong(w)
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

    for v in sorted(g):
        if v not in index:
            strong(v)
    return out


# --- the package -----------------------------------------------------------------------------------

def test_the_top_level_holds_only_the_entry_points():
    top = {p.stem for p in PKG.glob("*.py")}
    assert top <= TOP_LEVEL, f"modules at the top level beyond {sorted(TOP_LEVEL)}: {sorted(top - TOP_LEVEL)}"


def test_every_package_is_a_layer_and_every_layer_exists():
    tops = {m.split(".")[0] for m in modules(PKG)}
    assert tops == set(LAYERS), (sorted(tops - set(LAYERS)), sorted(set(LAYERS) - tops))


def test_no_module_imports_a_layer_above_its_own():
    bad = upward_imports(PKG)
    assert not bad, "\n".join(bad)


def test_no_import_cycle_between_modules():
    found = cycles(PKG)
    assert not found, "import cycles: " + "; ".join(" <-> ".join(c) for c in found)


def test_no_package_has_the_name_of_an_api_function():
    import symfunnel
    clash = sorted(n for n in symfunnel.__all__ if (PKG / n).is_dir() or (PKG / f"{n}.py").is_file())
    assert not clash, clash


def test_the_api_commands_are_plain_functions_with_signatures():
    import inspect
    import types

    import symfunnel
    for name in ("simulate", "codegen", "report", "verify", "audit", "sweep", "tune"):
        f = getattr(symfunnel, name)
        assert isinstance(f, types.FunctionType), (name, type(f))
        params = inspect.signature(f).parameters
        assert "scenario" in params and not any(p.kind is p.VAR_POSITIONAL for p in params.values()), name


# --- the checker catches what it is for --------------------------------------------------------------

def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    root = tmp_path / "pkg"
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text, encoding="utf-8")
    for d in [root] + [p for p in root.rglob("*") if p.is_dir()]:
        (d / "__init__.py").touch()
    return root


LOW_HIGH = ("low", "high", "__init__")


def test_the_checker_finds_a_function_local_upward_import(tmp_path):
    root = _tree(tmp_path, {"low/a.py": "def f():\n    from ..high import b\n    return b\n",
                            "high/b.py": "from ..low import a\n"})
    bad = upward_imports(root, LOW_HIGH)
    assert bad == ["low.a (low) imports high.b (high)"], bad


def test_the_checker_finds_an_importlib_upward_import(tmp_path):
    root = _tree(tmp_path, {"low/a.py": "import importlib\n\ndef f(n):\n"
                                        "    return importlib.import_module(f'pkg.high.{n}')\n",
                            "high/b.py": "x = 1\n"})
    assert any(s.startswith("low.a (low) imports high.b") for s in upward_imports(root, LOW_HIGH))


def test_the_checker_finds_a_cycle_through_a_function_local_import(tmp_path):
    root = _tree(tmp_path, {"low/a.py": "from . import b\n",
                            "low/b.py": "def f():\n    from .c import g\n    return g\n",
                            "low/c.py": "from .a import x\n"})
    assert cycles(root) == [["low.a", "low.b", "low.c"]]
    assert not upward_imports(root, LOW_HIGH)


def test_the_checker_accepts_a_clean_tree(tmp_path):
    root = _tree(tmp_path, {"low/a.py": "x = 1\n", "high/b.py": "from ..low.a import x\n"})
    assert not upward_imports(root, LOW_HIGH) and not cycles(root)


# --- the module map in docs/architecture.md -------------------------------------------------------

BEGIN = "<!-- module map: generated from the packages' docstrings by `python -m tests.test_architecture --write` -->"
END = "<!-- end of the module map -->"


def _docstring(path: Path) -> str:
    """The first paragraph of a module's docstring, on one line."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    return " ".join(doc.split("\n\n")[0].split())


def _first_sentence(path: Path) -> str:
    text = _docstring(path)
    cut = re.search(r"[.:;]\s+(?=[A-Z`(])", text)
    return text if cut is None else text[:cut.start() + 1]


def module_map(root: Path = PKG) -> str:
    """Markdown: the layers, lowest first, each with its docstring and its modules with their first sentences."""
    mods = modules(root)
    out = []
    for i, layer in enumerate(LAYERS):
        path = mods.get(layer)
        if path is None:
            continue
        is_pkg = path.name == "__init__.py" and layer != "__init__"
        out.append(f"{i + 1}. **`{layer}{'/' if is_pkg else '.py'}`**: {_docstring(path)}")
        for m in sorted(m for m in mods if m.startswith(layer + ".")):
            out.append(f"   - `{m[len(layer) + 1:]}`: {_first_sentence(mods[m])}")
    return "\n".join(out)


def _doc_with_map(text: str) -> str:
    head, _, rest = text.partition(BEGIN)
    _, _, tail = rest.partition(END)
    return f"{head}{BEGIN}\n{module_map()}\n{END}{tail}"


def test_docs_module_map_matches_the_packages():
    text = DOC.read_text(encoding="utf-8")
    assert BEGIN in text and END in text
    assert text == _doc_with_map(text), "docs/architecture.md is stale: run python -m tests.test_architecture --write"


def test_every_package_and_module_says_what_it_holds():
    missing = [m for m, p in modules(PKG).items() if not _first_sentence(p)]
    assert not missing, missing


@pytest.mark.parametrize("registry, key", [("symfunnel.family.transforms:TRANSFORMS", "design.transform"),
                                           ("symfunnel.family.approximators:APPROXIMATORS", "approximator.type"),
                                           ("symfunnel.family.funnels:FUNNEL_SHAPES", "funnel.eK"),
                                           ("symfunnel.family.variants:VARIANTS", "design.variant"),
                                           ("symfunnel.plant.engines:ENGINES", "plant.engine")])
def test_each_registry_is_documented_in_the_scenario_docs(registry, key):
    import importlib
    mod, name = registry.split(":")
    reg = getattr(importlib.import_module(mod), name)
    assert reg.key == key
    docs = (PKG.parent / "docs" / "scenario.md").read_text(encoding="utf-8")
    for entry in reg:
        assert f"`{entry.name}`" in docs, (key, entry.name)


#: the plant's equations (`plant.equations`): defined there once, imported from there by every loop that integrates them
PLANT_EQUATIONS = ("plant_acceleration", "plant_forces", "plant_parameters", "dead_zone_branches")


def test_the_plant_equations_live_in_plant_and_both_loops_import_them_from_there():
    defined = {}
    for mod, path in modules(PKG).items():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef) and node.name in PLANT_EQUATIONS:
                defined.setdefault(node.name, []).append(mod)
    assert defined == {name: ["plant.equations"] for name in PLANT_EQUATIONS}
    for loop in ("simulation.closedloop", "deployed.loop", "deployed.engine"):
        got = imports(loop, PKG / (loop.replace(".", "/") + ".py"))
        assert any(g.startswith("plant.equations") for g in got), (loop, sorted(got))
        assert not any(g.startswith("simulation.closedloop") for g in got if loop != "simulation.closedloop"), loop


def test_every_design_variant_name_has_its_class():
    from symfunnel.design import VARIANT_CLASSES, VARIANTS
    assert sorted(e.name for e in VARIANTS) == sorted(VARIANT_CLASSES)


if __name__ == "__main__":
    if "--write" in sys.argv:
        DOC.write_text(_doc_with_map(DOC.read_text(encoding="utf-8")), encoding="utf-8")
        print(f"wrote the module map into {DOC}")
    else:
        print(module_map())
