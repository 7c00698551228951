"""Child processes for library calls that can crash or hang the interpreter (pymeshlab's
reader and repairs, xatlas): started with this interpreter, their failure described in
one line here, where a crash becomes an error."""

from __future__ import annotations

import sys

from .interrupts import raise_if_child_interrupted


def python_command(*args: str) -> list[str]:
    """This interpreter running ``args`` (a script, or ``-m`` and a module) with ``-P``:
    the script's folder is not put first on the path, while the user's site-packages and
    PYTHONPATH stay, so a child finds its packages in a --user install or a studio's
    package environment (``-I`` dropped both)."""
    return [sys.executable, "-P", *args]


def child_failure(tool: str, returncode: int, stderr: str | None,
                  marker: str | None = None) -> str:
    """Why a child failed, in one line: its own refusal (the last stderr line starting
    with ``marker``, for a child that has refusals of its own), else the signal that
    killed it, else its exit code and the last line it wrote. A child ended by SIGINT
    raises KeyboardInterrupt: Ctrl-C, not a crash."""
    raise_if_child_interrupted(returncode)
    lines = (stderr or "").strip().splitlines()
    refused = [line[len(marker):].strip() for line in lines
               if marker and line.startswith(marker)]
    if refused:
        return refused[-1]
    if returncode < 0:
        return f"{tool} crashed (signal {-returncode})"
    return f"{tool} failed (exit {returncode}) {lines[-1][:200] if lines else ''}".rstrip()
