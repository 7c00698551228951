"""The package's layering (README "Layout"): stages import downwards only, nothing
imports the CLI, and no two modules import each other, directly or round a circle."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "skinpipe"
RANK = {"cli": 5, "workflow": 4, "capture": 3, "usd": 3, "render": 3, "profile": 2,
        "errors": 1, "fileio": 1, "imageio": 1, "package_data": 1, "interrupts": 1,
        "native": 1}
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


RENDER_RANK = {
    "renderer": 5, "outputs": 5, "frame": 5, "shading": 5,  # a frame's tasks and files
    "kernel_plan": 5,
    "diffusion": 4, "light": 3, "surface": 2,  # the algorithms
    "device": 1,  # OpenCL devices, programs, memory
    "scene": 0, "options": 0, "cache": 0, "bands": 0, "sorting": 0,  # plain data, caches
    "budget": 0,  # what a render may ask of the machine
}
"""Inside ``render/``: the algorithm above, the device and the caches below. A module
imports from its own rank or lower ranks only, never upwards; ``render/__init__`` is
empty."""


def _render_part(mod: str) -> str | None:
    parts = mod.split(".")
    return parts[2] if len(parts) > 2 and parts[1] == "render" else None


def test_every_render_module_has_a_rank() -> None:
    parts = {_render_part(m) for m in GRAPH} - {None}
    assert parts == set(RENDER_RANK), parts ^ set(RENDER_RANK)


def test_render_imports_downwards_only() -> None:
    bad = [(mod, t) for mod, targets in GRAPH.items() for t in targets
           if _render_part(mod) and _render_part(t)
           and RENDER_RANK[_render_part(t)] > RENDER_RANK[_render_part(mod)]]
    assert not bad


MAX_MODULE_LINES = 1000
"""A module longer than this holds more than one algorithm or concern (pbrt-v4's and
mitsuba3's file per algorithm): it is split by what its parts do. Generated tables
(tools/tabulate_*.py) are data, not code."""


def test_no_module_is_over_a_thousand_lines() -> None:
    long = {str(p.relative_to(PACKAGE)): n for p in PACKAGE.rglob("*.py")
            if (n := len((text := p.read_text()).splitlines())) > MAX_MODULE_LINES
            and not text.startswith('"""Generated by')}
    assert not long


MAX_RENDER_FUNCTION_LINES = 80
"""A function of ``render/`` longer than this (docstring included) does several steps
that read better named."""


def test_no_render_function_is_over_eighty_lines() -> None:
    long = {f"{p.relative_to(PACKAGE)}:{n.name}": n.end_lineno - n.lineno + 1
            for p in (PACKAGE / "render").rglob("*.py")
            for n in ast.walk(ast.parse(p.read_text()))
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef)
            and n.end_lineno - n.lineno + 1 > MAX_RENDER_FUNCTION_LINES}
    assert not long


def test_the_package_root_and_render_have_no_import_side_effects() -> None:
    """``import skinpipe`` and ``import skinpipe.render`` import nothing of skinpipe's own,
    so that the profile model loads without pxr, pyopencl or pymeshlab."""
    assert GRAPH["skinpipe"] <= {"skinpipe.__main__"} and not GRAPH["skinpipe.render"]


def test_the_profile_model_loads_without_pxr_or_opencl() -> None:
    code = ("import sys, skinpipe.profile.models, skinpipe.profile.fit; "
            "print(sorted(m for m in ('pxr', 'pyopencl', 'pymeshlab', 'embreex') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout.strip()
    assert out == "[]", out


def test_pymeshlab_is_imported_after_the_newer_tbb_only() -> None:
    """In-process, pymeshlab loads through skinpipe.native (its older TBB would hide
    Intel's OpenCL runtime); a child process that imports nothing else may import it."""
    bad = []
    for path in PACKAGE.rglob("*.py"):
        if path.name in ("native.py", "_meshlab_child.py"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module or ""] if isinstance(node, ast.ImportFrom) else []
            bad += [(path.name, n) for n in names if n.split(".")[0] == "pymeshlab"]
    assert not bad
