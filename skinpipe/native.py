"""Native libraries whose load order matters, loaded in that order.

Intel's CPU OpenCL runtime needs a TBB newer than the one pymeshlab ships (2021.5):
whichever ``libtbb.so.12`` a process loads first serves it, and with pymeshlab's the
runtime fails to load and its OpenCL platform silently disappears. The ``tbb``
package's library (installed with ``skinpipe[intel-cpu]``) is therefore loaded before
pymeshlab wherever either is used; pymeshlab runs on the newer one (TBB keeps its ABI
within a major version). Every in-process import of pymeshlab goes through
:func:`import_pymeshlab`.
"""

from __future__ import annotations

import ctypes
import sys
from functools import lru_cache
from importlib import metadata
from pathlib import Path
from types import ModuleType

TBB_DIST, TBB_LIBRARY = "tbb", "libtbb.so.12"


def dist_file(dist: str, name: str) -> Path | None:
    """Absolute path of the file ``name`` installed by distribution ``dist``, if any."""
    try:
        files = metadata.distribution(dist).files or []
    except metadata.PackageNotFoundError:
        return None
    for f in files:
        if f.name == name:
            path = Path(str(f.locate())).resolve()
            if path.is_file():
                return path
    return None


@lru_cache(maxsize=1)
def load_newer_tbb() -> str | None:
    """Load the ``tbb`` package's library into the process (once); a note saying why it
    could not be, or None (loaded, or not installed: nothing needs it then)."""
    tbb = dist_file(TBB_DIST, TBB_LIBRARY)
    if tbb is None:
        return None
    if "pymeshlab" in sys.modules:
        return ("pymeshlab was loaded first with its older TBB; import it through "
                "skinpipe.native.import_pymeshlab")
    try:
        ctypes.CDLL(str(tbb), mode=ctypes.RTLD_GLOBAL)
    except OSError as exc:
        return f"cannot load {tbb}: {exc}"
    return None


def import_pymeshlab() -> ModuleType:
    """pymeshlab, imported after the newer TBB (:func:`load_newer_tbb`)."""
    load_newer_tbb()
    import pymeshlab

    return pymeshlab


def pymeshlab_folder() -> Path:
    """pymeshlab's installed folder, found without importing it (0.07 s, and its TBB)."""
    import importlib.util

    spec = importlib.util.find_spec("pymeshlab")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("pymeshlab is not installed")
    return Path(next(iter(spec.submodule_search_locations)))
