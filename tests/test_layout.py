"""The package's layout (docs/design.md, "Layers"): read from the code's own imports.

Layers, bottom to top; a module may import from a lower layer or from its own package, never upward
and never sideways into another package of its layer:

  0 core      types, errors, _xla_flags, version, autodiff
  1 base      paths, environment, io, cameras, metrics
  2 data      scenes (one module per format), weights; search (poses and scores only: no renderer,
              no criterion)
  3 render    the volume integral, occupancy marching, the marched renderer, sharding
  4 models    nerf (hash grid, field, training, checkpoints, run directories), procedural (the room),
              splats (3D Gaussian splats: files, the tile renderer, fitting, splat runs)
  5 criteria  what scores a view
  6 pipeline  sources, experiments (source + criterion + method), their files, the demo
  7 viewer    the 3D viewer (viser) of runs and scenes
  8 cli       one module per command
"""

from __future__ import annotations

import ast
import importlib
import inspect
from pathlib import Path
from typing import Dict, List, Set, Tuple

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "waldo_jax"

LAYERS = {
    "waldo_jax.types": 0,
    "waldo_jax.errors": 0,
    "waldo_jax._xla_flags": 0,
    "waldo_jax.version": 0,
    "waldo_jax.autodiff": 0,
    "waldo_jax.paths": 1,
    "waldo_jax.environment": 1,
    "waldo_jax.io": 1,
    "waldo_jax.cameras": 1,
    "waldo_jax.metrics": 1,
    "waldo_jax.scenes": 2,
    "waldo_jax.weights": 2,
    "waldo_jax.search": 2,
    "waldo_jax.render": 3,
    "waldo_jax.nerf": 4,
    "waldo_jax.procedural": 4,
    "waldo_jax.splats": 4,
    "waldo_jax.criteria": 5,
    "waldo_jax.pipeline": 6,
    "waldo_jax.viewer": 7,
    "waldo_jax.cli": 8,
    "waldo_jax": 9,
    "waldo_jax.__main__": 9,
}


def _modules() -> Dict[str, Path]:
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        modules[".".join(parts)] = path
    return modules


MODULES = _modules()


def _resolve(name: str) -> str:
    """The module of the repository that `name` (a module or a name inside one) lives in."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name


def _imports(module: str, path: Path) -> List[Tuple[str, str, int]]:
    """(imported module, imported name or "", line) of every waldo_jax import in `path` (functions too)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source.split(".")[0] != "waldo_jax":
                continue
            for alias in node.names:
                full = f"{source}.{alias.name}"
                if full in MODULES:  # `from package import module`
                    found.append((full, "", node.lineno))
                else:
                    found.append((_resolve(source), alias.name, node.lineno))
        elif isinstance(node, ast.Import):
            found += [(_resolve(a.name), "", node.lineno) for a in node.names if a.name.split(".")[0] == "waldo_jax"]
    return found


def _unit(module: str) -> str:
    """The layer entry a module belongs to (its package, or itself)."""
    while module not in LAYERS:
        module = module.rpartition(".")[0]
    return module


def _graph() -> Dict[str, Set[str]]:
    return {m: {target for target, _, _ in _imports(m, p) if target != m} for m, p in MODULES.items()}


def test_every_module_has_a_layer():
    assert all(_unit(m) in LAYERS for m in MODULES)


@pytest.mark.slow
def test_no_import_runs_upward_or_sideways():
    wrong = []
    for module, path in MODULES.items():
        unit = _unit(module)
        for target, _, line in _imports(module, path):
            other = _unit(target)
            if other != unit and LAYERS[other] >= LAYERS[unit]:
                wrong.append(
                    f"{path.relative_to(ROOT)}:{line}: {unit} (layer {LAYERS[unit]}) imports {target} "
                    f"(layer {LAYERS[other]})"
                )
    assert not wrong, "\n".join(wrong)


@pytest.mark.slow
def test_no_import_cycle():
    graph = _graph()
    state: Dict[str, int] = {}
    stack: List[str] = []
    cycles = []

    def visit(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(" -> ".join(stack[stack.index(nxt) :] + [nxt]))
            elif nxt not in state:
                visit(nxt)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            visit(node)
    assert not cycles, "\n".join(cycles)


def _users() -> List[Tuple[Path, str, str, int]]:
    """(file, module, name, line) of every `from waldo_jax... import name` in the package and the benchmarks."""
    uses = []
    for module, path in MODULES.items():
        uses += [(path, target, name, line) for target, name, line in _imports(module, path) if target != module]
    for path in sorted((ROOT / "benchmarks").glob("*.py")):
        uses += [(path, target, name, line) for target, name, line in _imports(path.stem, path)]
    return uses


@pytest.mark.slow
def test_no_private_name_crosses_a_module():
    private = [
        f"{path.relative_to(ROOT)}:{line}: {module}.{name}"
        for path, module, name, line in _users()
        if name.startswith("_") and not name.startswith("__")
    ]
    attributes = []
    for path in [*MODULES.values(), *sorted((ROOT / "benchmarks").glob("*.py"))]:
        tree = ast.parse(path.read_text())
        imported = set()  # the names an import of waldo_jax binds: `import waldo_jax.a.b` binds waldo_jax
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("waldo_jax"):
                imported |= {alias.asname or alias.name for alias in node.names}
            elif isinstance(node, ast.Import):
                imported |= {
                    alias.asname or alias.name.split(".")[0]
                    for alias in node.names
                    if alias.name.startswith("waldo_jax")
                }
        for node in ast.walk(tree):
            root = node.value if isinstance(node, ast.Attribute) else None
            while isinstance(root, ast.Attribute):  # waldo_jax.nerf.step._x: down to the bound name
                root = root.value
            hidden = isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
            if hidden and isinstance(root, ast.Name) and root.id in imported:
                attributes.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id == "getattr"
                and len(node.args) >= 2
                and isinstance(node.args[0], ast.Name)
                and node.args[0].id in imported
                and isinstance(node.args[1], ast.Constant)
                and str(node.args[1].value).startswith("_")
            ):
                attributes.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)}")
    assert not private + attributes, "\n".join(private + attributes)


@pytest.mark.slow
def test_names_used_across_modules_are_documented():
    missing = []
    for path, module, name, line in _users():
        if not name or name == "*":
            continue
        obj = getattr(importlib.import_module(module), name, None)
        if (inspect.isfunction(obj) or inspect.isclass(obj)) and not inspect.getdoc(obj):
            missing.append(f"{path.relative_to(ROOT)}:{line}: {module}.{name}")
    assert not missing, "\n".join(missing)


@pytest.mark.parametrize("name", ["load_scene", "read_poses_file"])
def test_the_public_api_keeps_its_names(name):
    import waldo_jax.criteria as criteria
    import waldo_jax.render as render
    import waldo_jax.scenes as scenes
    import waldo_jax.search as search

    assert callable(getattr(scenes, name))
    assert callable(search.explore) and "egps" in search.METHODS
    assert "saliency" in criteria.CRITERIA and callable(criteria.make_criterion)
    assert callable(render.render_views) and callable(render.render_marched)


MAX_PARAMETERS = 8  # of a public function or method: positional and keyword-only, not self / cls, *args, **kwargs
MAX_LINES = 80  # of any function, from its `def` to its last line (decorators excluded)


def _oversized(source: str, where: str) -> List[str]:
    """'where:line: ...' of each public function in `source` over MAX_PARAMETERS parameters, and of each
    function (public or private, nested ones and methods too) over MAX_LINES lines.

    A function's length counts the lines on which its statements start (the def line included), not
    its physical lines: ruff's formatter spreads a long call over one line per argument, and a split
    should follow the function's seams, not the formatter's line breaks."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        args = node.args
        count = sum(a.arg not in ("self", "cls") for a in args.posonlyargs + args.args + args.kwonlyargs)
        if not node.name.startswith("_") and count > MAX_PARAMETERS:
            found.append(f"{where}:{node.lineno}: {node.name} takes {count} parameters (at most {MAX_PARAMETERS})")
        lines = len({n.lineno for n in ast.walk(node) if isinstance(n, ast.stmt)})
        if lines > MAX_LINES:
            found.append(f"{where}:{node.lineno}: {node.name} is {lines} lines long (at most {MAX_LINES})")
    return found


def test_oversized_counts_parameters_and_lines_as_documented():
    eight = "self, a, /, b, c, *args, d, e, f, g, h{}, **kwargs"  # self, *args and **kwargs not counted
    assert _oversized(f"class A:\n    def m({eight.format('')}):\n        pass\n", "x") == []
    nine = eight.format(", i")
    assert _oversized(f"class A:\n    def m({nine}):\n        pass\n", "x") == ["x:2: m takes 9 parameters (at most 8)"]
    assert _oversized(f"def _f({nine}):\n    pass\n", "x") == []  # private: any number
    body = "".join(f"    x = {i}\n" for i in range(MAX_LINES - 1))
    assert _oversized(f"@decorator\ndef _f():\n{body}", "x") == []
    assert _oversized(f"def _f():\n{body}    x = 0\n", "x") == ["x:1: _f is 81 lines long (at most 80)"]
    spread = "".join(f"    x = f(\n        {i},\n    )\n" for i in range(MAX_LINES - 1))  # a statement over 3 lines
    assert _oversized(f"def _f():\n{spread}", "x") == []


@pytest.mark.slow
def test_no_public_function_over_8_parameters_and_no_function_over_80_lines():
    found = []
    for path in MODULES.values():
        found += _oversized(path.read_text(), str(path.relative_to(ROOT)))
    assert not found, "\n".join(found)
