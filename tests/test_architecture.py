"""The shape of the house (docs/architecture.md §2): imports go one way, nothing is circular,
modules stay small and folders stay walkable.

Every ``import`` of the source packages is read with :mod:`ast` (module level and inside
functions alike), resolved to a project module, and checked against the layer ranks below: a
unit may import its own unit and units of a strictly lower rank, nothing else.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

from tests.conftest import PROJECT_ROOT

PACKAGES = ("calib", "drivers", "sim_devices", "acquire", "office", "cli")

#: top-level packages: calib ← drivers ← sim_devices / acquire (the vessel) ← office ← cli
PACKAGE_RANK = {"calib": 0, "drivers": 1, "sim_devices": 2, "acquire": 2, "office": 3, "cli": 4}

#: units inside a package (a subpackage or a top-level module) and their ranks
UNIT_RANK = {
    "calib": {
        "core": 0,
        "io": 1,
        "survey": 2,
        "extraction": 2,
        "sim": 3,
        "boresight": 3,
        "assess": 3,
        "design": 4,
        "watch": 4,
    },
    "drivers": {
        "base": 0,
        "timing": 0,
        "ppsfetch": 0,
        "hydrins": 1,
        "zf": 1,
        "pps": 1,
        "can": 1,
        "transport": 2,
        "capture": 2,
    },
    "acquire": {
        "alarms": 0,
        "errors": 0,
        "timing": 1,
        "log": 2,
        "status": 3,
        "daemon": 4,
        "guidance": 5,
        "ui": 5,
        "watch": 5,
        "doctor": 5,
        "console": 5,
        "foxglove": 5,
    },
    "office": {
        "simsession": 0,
        "jobs": 1,
        "deliver": 2,
    },
}

MAX_MODULE_LINES = 600
MAX_MODULES_PER_FOLDER = 16


def _modules() -> dict[str, Path]:
    mods = {}
    for pkg in PACKAGES:
        for path in (PROJECT_ROOT / pkg).rglob("*.py"):
            parts = path.relative_to(PROJECT_ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join(parts)] = path
    return mods


MODULES = _modules()


def _imports(name: str, path: Path) -> set[str]:
    """Project modules that ``name`` imports (``from pkg import mod`` counts as ``pkg.mod``)."""
    out: set[str] = set()
    is_pkg = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".")
                base = base[: len(base) - node.level + (1 if is_pkg else 0)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            targets = [module] + [f"{module}.{a.name}" for a in node.names]
        else:
            continue
        for t in targets:
            # the longest project module that the dotted name starts with
            while t and t not in MODULES:
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


GRAPH = {name: _imports(name, path) for name, path in MODULES.items()}


def _unit(module: str) -> tuple[str, str | None]:
    parts = module.split(".")
    return parts[0], (parts[1] if len(parts) > 1 else None)


def test_the_graph_is_read():
    # a broken reader would pass every check below vacuously
    assert len(MODULES) > 100
    assert "calib.core.frames" in GRAPH["calib.io.site"]
    assert "drivers.hydrins.nav" in GRAPH["sim_devices.feed"]


def test_no_import_from_a_lower_layer_to_a_higher_one():
    bad = []
    for mod, deps in GRAPH.items():
        pkg, unit = _unit(mod)
        for dep in deps:
            dpkg, dunit = _unit(dep)
            if dpkg != pkg:
                if PACKAGE_RANK[dpkg] >= PACKAGE_RANK[pkg]:
                    bad.append(f"{mod} imports {dep} ({pkg} may not import {dpkg})")
                continue
            ranks = UNIT_RANK.get(pkg)
            if ranks is None or unit is None or dunit is None or unit == dunit:
                continue
            if unit not in ranks or dunit not in ranks:
                bad.append(
                    f"{mod} / {dep}: unit without a rank in UNIT_RANK (add it there and to "
                    f"docs/architecture.md §2)"
                )
            elif ranks[dunit] >= ranks[unit]:
                bad.append(f"{mod} imports {dep} ({pkg}.{unit} may not import {pkg}.{dunit})")
    assert not bad, "\n".join(sorted(bad))


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
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


def test_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_cycles():
    # a package's __init__ re-exporting its modules is not a cycle of the code
    graph = defaultdict(set)
    for mod, deps in GRAPH.items():
        graph[mod] = {d for d in deps if not mod.startswith(d + ".")}
    assert _cycles(graph) == []


@pytest.mark.parametrize("pkg", PACKAGES)
def test_modules_stay_small_and_folders_walkable(pkg):
    long = [
        f"{p.relative_to(PROJECT_ROOT)}: {n} lines"
        for p in (PROJECT_ROOT / pkg).rglob("*.py")
        if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES
    ]
    assert not long, f"modules over {MAX_MODULE_LINES} lines:\n" + "\n".join(long)
    crowded = [
        f"{d.relative_to(PROJECT_ROOT)}: {n} modules"
        for d in [PROJECT_ROOT / pkg, *(PROJECT_ROOT / pkg).rglob("*/")]
        if d.is_dir() and (n := len(list(d.glob("*.py")))) > MAX_MODULES_PER_FOLDER
    ]
    assert not crowded, f"folders over {MAX_MODULES_PER_FOLDER} modules:\n" + "\n".join(crowded)


MAX_FUNCTION_BODY_LINES = 60


def _body_lines(node: ast.FunctionDef | ast.AsyncFunctionDef) -> int:
    """Lines from the first statement after the docstring to the function's end (the signature
    and the docstring do not count: a typer command's options are declarations, not work)."""
    body = node.body
    first = body[0]
    is_docstring = isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
    if is_docstring and isinstance(first.value.value, str) and len(body) > 1:
        first = body[1]
    assert node.end_lineno is not None
    return node.end_lineno - first.lineno + 1


def _long_functions(path: Path, root: Path = PROJECT_ROOT) -> list[str]:
    tree = ast.parse(path.read_text())
    return [
        f"{path.relative_to(root)}:{node.lineno} {node.name}: {n} lines"
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and (n := _body_lines(node)) > MAX_FUNCTION_BODY_LINES
    ]


def test_long_function_finder_finds_one(tmp_path):
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_FUNCTION_BODY_LINES + 1))
    (tmp_path / "m.py").write_text(f'def short():\n    """Doc."""\n    return 1\n\n\ndef long():\n{body}\n')
    assert _long_functions(tmp_path / "m.py", tmp_path) == [
        f"m.py:6 long: {MAX_FUNCTION_BODY_LINES + 1} lines"
    ]


@pytest.mark.parametrize("pkg", PACKAGES)
def test_functions_stay_short(pkg):
    """Functions of one idea: no library function's body is over 60 lines (docs/architecture.md §2)."""
    long = [line for p in sorted((PROJECT_ROOT / pkg).rglob("*.py")) for line in _long_functions(p)]
    assert not long, f"functions over {MAX_FUNCTION_BODY_LINES} lines:\n" + "\n".join(long)
