"""Folders that ship inside the package (package data: the USD schema, the usdview
plugin, the demo's sample captures), found with :mod:`importlib.resources` so that a
wheel installed anywhere finds them as a checkout does."""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from .errors import SkinpipeError


def package_folder(*parts: str) -> Path:
    """The folder ``skinpipe/<parts...>`` of this installation, as a file-system path
    (USD's plugin registry and the stage readers need real files)."""
    folder = files("skinpipe").joinpath(*parts)
    path = Path(str(folder))
    if not path.is_dir():
        raise SkinpipeError(f"{path}: this skinpipe installation lacks its package data "
                            f"{'/'.join(parts)!r} (a zipped or partial install?); "
                            "reinstall skinpipe with pip")
    return path
