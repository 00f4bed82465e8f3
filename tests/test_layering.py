"""The layering the code promises (docs/DESIGN.md), read from the source: no import cycle and no import inside a
function whose module imports the importer back; the core imports no DuckDB, no file-system module and nothing
above it; no function takes more than seven parameters."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "prism_stream"


def _modules() -> dict[str, Path]:
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(ROOT).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


MODULES = _modules()


def _targets(module: str, node) -> list[str]:
    """The project modules an import statement of ``module`` names."""
    package = module if MODULES[module].name == "__init__.py" else module.rsplit(".", 1)[0]
    if isinstance(node, ast.ImportFrom):
        if node.level:
            base = ".".join(package.split(".")[:len(package.split(".")) - node.level + 1] + ([node.module] if node.module else []))
        else:
            base = node.module or ""
        found = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        return [m for m in found if m in MODULES]
    return [a.name for a in node.names if a.name in MODULES]


def _graph():
    top, inner = {}, {}
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        top[module], inner[module] = set(), []
        functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
        in_functions = {id(n) for f in functions for n in ast.walk(f)}
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                if id(node) in in_functions:
                    inner[module] += [(node.lineno, t) for t in _targets(module, node)]
                else:
                    top[module] |= set(_targets(module, node))
    return top, inner


def _reaches(top: dict, start: str, goal: str) -> bool:
    seen, todo = set(), [start]
    while todo:
        m = todo.pop()
        if m == goal:
            return True
        if m not in seen:
            seen.add(m)
            todo += top.get(m, ())
    return False


def test_no_import_cycle_and_no_import_that_only_breaks_one():
    top, inner = _graph()
    cycles = sorted({tuple(sorted((m, t))) for m in top for t in top[m] if t != m and _reaches(top, t, m)})
    assert not cycles, f"modules that import each other: {cycles}"
    breakers = [f"{m}:{line} -> {t}" for m, found in inner.items() for line, t in found
                if t != m and _reaches(top, t, m)]
    assert not breakers, f"imports inside functions whose target imports the importer back: {breakers}"


def test_the_core_does_no_io_and_imports_nothing_above_it():
    allowed_outside = {"prism_stream.errors"}
    banned = {"duckdb", "os", "shutil", "tempfile", "pathlib", "io", "glob"}
    for module, path in MODULES.items():
        if not module.startswith("prism_stream.core"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name.split(".")[0] for a in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [(node.module or "").split(".")[0]]
            else:
                names = []
            assert not set(names) & banned, f"{module} imports {names}: the core does no I/O"
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for target in _targets(module, node):
                    assert target.startswith("prism_stream.core") or target in allowed_outside, \
                        f"{module} imports {target}, above the core"


def test_at_most_seven_parameters():
    """The numba loops too: their arrays come in tuples by role (core/jit.py), which numba unpacks at no cost."""
    wide = []
    for root in (PACKAGE, ROOT / "cli"):
        for path in root.rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    a = node.args
                    names = [x.arg for x in a.posonlyargs + a.args + a.kwonlyargs if x.arg not in ("self", "cls")]
                    if len(names) > 7:
                        wide.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name} ({len(names)})")
    assert not wide, f"functions with more than seven parameters: {wide}"
