"""The package's import structure: no import cycle (function-local imports included, so a lazy import cannot
hide a back edge), and the core never imports its callers (the ROS node, the command modules, the CLI) or rclpy."""
from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "gd_completion"
ROOT = "gd_completion"
CALLERS = ("gd_completion.ros", "gd_completion.tools", "gd_completion.cli")
RCLPY_ALLOWED = ("gd_completion.ros", "gd_completion.tools.play")


def module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def imports(name: str, path: Path, known: set[str]) -> list[tuple[str, int, bool]]:
    """(imported module, line, function-local) for every import of `name` (absolute, resolved)."""
    tree = ast.parse(path.read_text())
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    local_lines = {n.lineno for f in ast.walk(tree) if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef))
                   for n in ast.walk(f) if isinstance(n, (ast.Import, ast.ImportFrom))}
    out = []
    for node in ast.walk(tree):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parent = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(parent + ([base] if base else []))
            targets = [base] + [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in known]
        else:
            continue
        for target in targets:
            out.append((target, node.lineno, node.lineno in local_lines))
    return out


def graph() -> tuple[dict[str, set[str]], dict[tuple[str, str], tuple[int, bool]]]:
    """Module -> the package modules it imports (with the packages whose __init__ that runs, except its own
    ancestors: those are initialised already); and (from, to) -> (line, function-local)."""
    found = modules()
    known = set(found)
    edges: dict[str, set[str]] = {m: set() for m in known}
    where: dict[tuple[str, str], tuple[int, bool]] = {}
    for name, path in found.items():
        ancestors = {".".join(name.split(".")[:i]) for i in range(1, name.count(".") + 1)}
        for target, line, local in imports(name, path, known):
            parts = target.split(".")
            for i in range(1, len(parts) + 1):
                prefix = ".".join(parts[:i])
                if prefix == ROOT:   # the root package's __init__ only re-exports lazily (on attribute access)
                    continue
                if prefix in known and prefix != name and (prefix == target or prefix not in ancestors):
                    if prefix not in ancestors or prefix == target:
                        edges[name].add(prefix)
                        where.setdefault((name, prefix), (line, local))
    return edges, where


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
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
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_no_import_cycles_local_imports_included() -> None:
    edges, where = graph()
    found = cycles(edges)
    detail = [[f"{a} -> {b} (line {where[(a, b)][0]}{', in a function' if where[(a, b)][1] else ''})"
               for a in c for b in sorted(edges[a]) if b in c] for c in found]
    assert not found, detail


def test_core_does_not_import_its_callers_or_rclpy() -> None:
    found = modules()
    bad = []
    for name, path in found.items():
        if name.startswith(CALLERS):
            continue
        for target, line, _ in imports(name, path, set(found)):
            if target.startswith(CALLERS) or (target.split(".")[0] == "rclpy" and not name.startswith(RCLPY_ALLOWED)):
                bad.append(f"{name}:{line} imports {target}")
    assert not bad, bad


def test_the_checker_finds_a_cycle_through_a_local_import() -> None:
    edges = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(edges) == [["a", "b", "c"]]
