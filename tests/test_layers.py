"""The package's layering (README "Layout"): stages import downwards only, nothing
imports the CLI, and no two modules import each other, directly or round a circle."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "skinpipe"
RANK = {"cli": 5, "workflow": 4, "capture": 3, "usd": 3, "render": 3, "profile": 2,
        "errors": 1, "fileio": 1, "imageio": 1, "package_data": 1}
ALSO_ALLOWED = {("render", "usd")}
"""Sideways imports allowed: the render reads USD stages (scene delegate, guarded opens,
mesh checks)."""


def _module(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every skinpipe module ``path`` imports, at its head or inside a function."""
    mod = _module(path)
    pkg = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                target = ".".join([*base, *([node.module] if node.module else [])])
            else:
                target = node.module or ""
            names = [f"{target}.{a.name}" for a in node.names]
            out |= {n for n in [target, *names] if _exists(n)}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names if _exists(a.name)}
    return {m for m in out if m.startswith("skinpipe") and m != mod}


def _exists(name: str) -> bool:
    rel = Path(*name.split(".")[1:]) if "." in name else Path()
    return name.startswith("skinpipe") and (
        (PACKAGE / rel).with_suffix(".py").is_file() or (PACKAGE / rel / "__init__.py").is_file())


GRAPH = {_module(p): _imports(p) for p in PACKAGE.rglob("*.py")}


def _layer(mod: str) -> str | None:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in RANK else None


def test_nothing_outside_the_cli_imports_it() -> None:
    bad = [(m, t) for m, ts in GRAPH.items() for t in ts
           if _layer(t) == "cli" and _layer(m) != "cli" and m != "skinpipe.__main__"]
    assert not bad


def test_stages_import_downwards_only() -> None:
    bad = []
    for mod, targets in GRAPH.items():
        a = _layer(mod)
        for t in targets:
            b = _layer(t)
            if a is None or b is None or a == b or (a, b) in ALSO_ALLOWED:
                continue
            if RANK[b] > RANK[a] or (RANK[b] == RANK[a] > 1):  # shared utilities may share
                bad.append((mod, t))
    assert not bad


def test_no_import_circles() -> None:
    # a module's own enclosing packages are left out: importing them is how Python
    # reaches the module at all
    graph = {m: {t for t in ts if t in GRAPH and not m.startswith(t + ".")}
             for m, ts in GRAPH.items()}
    state: dict[str, int] = {}
    circles: list[list[str]] = []

    def visit(m: str, stack: list[str]) -> None:
        state[m] = 1
        for t in sorted(graph.get(m, ())):
            if state.get(t) == 1:
                circles.append([*stack[stack.index(t):], t] if t in stack else [m, t])
            elif t not in state:
                visit(t, [*stack, t])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])
    assert not circles
