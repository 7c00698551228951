"""OpenCL C sources, kept as ``.cl`` files beside the modules that build them (package
data, read with :mod:`importlib.resources`).

A line that is exactly ``#include "NAME.cl"`` is replaced by that file's source (from the
same folder, else from this one) before the program is built: the shared pieces (half
floats by their bits, streaming stores) reach every program as text, so that a
program's source, and with it the runtimes' caches of what they built, depend on
nothing but the files."""

from __future__ import annotations

import re
from functools import cache
from importlib.resources import files

_INCLUDE = re.compile(r'^#include "([A-Za-z0-9_]+\.cl)"\n', re.M)


@cache
def cl_source(package: str, name: str) -> str:
    """The source of ``name`` in ``package``'s folder, its includes expanded."""
    text = files(package).joinpath(name).read_text(encoding="utf-8")

    def include(match: re.Match[str]) -> str:
        wanted = match.group(1)
        here = files(package).joinpath(wanted)
        return cl_source(package if here.is_file() else __package__, wanted)

    return _INCLUDE.sub(include, text)
