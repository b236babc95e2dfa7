"""The package's structure: one-way layers, no import cycles, kernels in one place, no hidden
stage protocol. Static checks over the source (imports inside functions count too)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "stereocli"

#: The layering (README, Architecture): a module may import its own layer or lower ones.
#: cli → jobs → api → {matching, rectification, triangulation, evaluation, calib, synth, features} → {io,
#: registry, config, viz, runinfo, process, runtime} → errors
LAYERS = {
    "errors": 0, "lazy": 0,
    "io": 1, "registry": 1, "config": 1, "viz": 1, "runinfo": 1, "process": 1, "runtime": 1,
    "matching": 2, "rectification": 2, "triangulation": 2, "evaluation": 2, "calib": 2, "synth": 2, "features": 2,
    "api": 3, "apidoc": 3, "sequence": 3,
    "jobs": 4,
    "cli": 5,
    "__main__": 6,
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


MODULES = {_module_name(p): p for p in PACKAGE.rglob("*.py")}


def _imports(module: str) -> set[str]:
    """Every stereocli module ``module`` imports, at module level or inside functions."""
    path = MODULES[module]
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for target in targets:
            while target and target not in MODULES:
                target = target.rpartition(".")[0]
            if target.startswith("stereocli") and target != module:
                found.add(target)
    return found


GRAPH = {m: _imports(m) for m in MODULES}


def _layer(module: str) -> int | None:
    parts = module.split(".")
    return LAYERS.get(parts[1]) if len(parts) > 1 else None


def test_every_top_level_module_has_a_layer():
    tops = {m.split(".")[1] for m in MODULES if "." in m}
    assert tops <= set(LAYERS), f"give these a layer in LAYERS (and the README): {sorted(tops - set(LAYERS))}"


def test_imports_go_down_the_layers():
    upward = [f"{m} -> {d}" for m, deps in GRAPH.items() for d in deps
              if _layer(m) is not None and _layer(d) is not None and _layer(d) > _layer(m)]
    assert not upward, "imports against the layering:\n" + "\n".join(sorted(upward))


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import cycles of ``graph``: Tarjan's strongly connected components of more than one node."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
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
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return cycles


def _package(module: str) -> str:
    """The top-level package (or module) of stereocli that ``module`` belongs to."""
    return ".".join(module.split(".")[:2])


def test_no_import_cycles():
    cycles = _cycles(GRAPH)
    assert not cycles, f"import cycles: {cycles}"


def test_no_import_cycles_between_packages():
    # Package level: matching importing features while features imports matching is a cycle even
    # when no two modules import each other.
    graph: dict[str, set[str]] = {}
    for module, deps in GRAPH.items():
        graph.setdefault(_package(module), set()).update(_package(d) for d in deps if _package(d) != _package(module))
    for package in list(graph.values()):
        for target in package:
            graph.setdefault(target, set())
    cycles = _cycles(graph)
    assert not cycles, f"import cycles between packages: {cycles}"


def test_the_cycle_check_finds_a_cycle():
    # The checker itself: a graph with a cycle must be reported (guards against a vacuous pass),
    # and modules of two packages that import each other's package make a package cycle.
    assert _cycles({"a": {"b"}, "b": {"a"}, "c": set()}) == [["a", "b"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
    assert _package("stereocli.matching.kernels.sgm") == "stereocli.matching" and _package("stereocli") == "stereocli"


def test_the_library_never_imports_click():
    offenders = []
    for module, path in MODULES.items():
        if module.startswith("stereocli.cli"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "click" for n in names):
                offenders.append(module)
    assert not offenders


def _decorator_names(node: ast.AST) -> list[str]:
    out = []
    for d in getattr(node, "decorator_list", []):
        d = d.func if isinstance(d, ast.Call) else d
        out.append(d.attr if isinstance(d, ast.Attribute) else getattr(d, "id", ""))
    return out


def test_compiled_kernels_live_in_kernel_modules():
    misplaced = [f"{m}.{n.name}" for m, p in MODULES.items() for n in ast.walk(ast.parse(p.read_text()))
                 if "njit" in _decorator_names(n) and not (".kernels." in m or m.endswith(".kernels"))]
    assert not misplaced, f"@njit outside a kernels module: {misplaced}"


def test_no_attribute_is_set_on_a_function_after_its_definition():
    found = []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        functions = {n.name for n in tree.body if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [getattr(node, "target", None)]
            for t in targets:
                if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id in functions:
                    found.append(f"{module}: {t.value.id}.{t.attr}")
    assert not found, "declare these as StageTraits at registration: " + ", ".join(found)


@pytest.mark.parametrize("module", ["stereocli.matching.pipeline", "stereocli.matching.config"])
def test_the_pipeline_never_tests_a_stage_name(module):
    tree = ast.parse(MODULES[module].read_text())
    tests = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Compare)
             and any(isinstance(x, ast.Attribute) and x.attr == "name" for x in [n.left, *n.comparators])]
    assert not tests
