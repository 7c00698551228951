"""OpenCL runtimes that skinpipe installs, registered with the ICD loader before the first
platform query.

pyopencl's wheel brings PoCL 3.0 (LLVM 14), which cannot build a program on CPUs newer
than its LLVM (AMD Zen 5: "unknown target CPU 'generic'", pocl/pocl issue 1049). The
second CPU runtime is Intel's (``intel-opencl-rt`` on the package index; Intel's EULA,
not open source), which pip installs into ``<prefix>/lib`` without an ICD entry the
loader can use (its ``.icd`` files hold a build machine's path). This module writes a
vendors folder holding an entry with the library's absolute path plus the machine's own
entries (``/etc/OpenCL/vendors``: GPU drivers), and points ``OCL_ICD_VENDORS`` at it.
The loader reads that variable once per process, at the first platform query, and child
processes (Dask workers) inherit it; pyopencl's loader adds its own PoCL whatever the
folder holds. Nothing here imports pyopencl.

The folder is written at the first platform query (:func:`register_vendors`, called by
:func:`~.opencl.candidates`), not at import: Intel's runtime is loaded only where it may
be used. Once PoCL has passed skinpipe's probe on this CPU (a record in the cache folder,
:func:`pocl_passed_here`), a render asking for ``auto``, ``cpu``, ``gpu`` or PoCL leaves
it out: loaded, its library and LLVM are 85 MiB of the process's memory and 25 ms of its
start, for a device that PoCL ranks ahead of.

Intel's runtime needs a TBB newer than the one pymeshlab ships (2021.5): whichever
``libtbb.so.12`` is loaded first serves the process, and with pymeshlab's the runtime
fails to load and its platform silently disappears. The ``tbb`` package's library is
therefore loaded first (pymeshlab runs on the newer one: TBB keeps its ABI within a
major version).
"""

from __future__ import annotations

import atexit
import hashlib
import importlib.util
import os
import sys
import tempfile
from dataclasses import dataclass, field
from functools import lru_cache
from importlib import metadata
from pathlib import Path

from ...fileio import atomic_write_text
from ...native import dist_file, load_newer_tbb
from ..cache import GuardedTree, cache_root, settle_cache_root

ICD_ENV = "OCL_ICD_VENDORS"
POCL_CACHE_ENV = "POCL_CACHE_DIR"
SYSTEM_VENDORS = Path("/etc/OpenCL/vendors")
INTEL_DIST, INTEL_LIBRARY = "intel-opencl-rt", "libintelocl.so"


@dataclass
class RuntimeSetup:
    """What :func:`register_runtimes` and :func:`register_vendors` did: the vendors
    folder used, one note per runtime that could not be registered or was left out
    (shown by ``skinpipe env`` and in "no device" errors), Intel's library if installed,
    and whether the loader's vendors are settled (its first platform query came)."""

    vendors: str | None = None
    notes: list[str] = field(default_factory=list)
    intel: Path | None = None
    user_vendors: bool = False
    settled: bool = False
    intel_left_out: bool = False

    def note(self, text: str) -> None:
        """Add ``text`` to :attr:`notes` once (a process may ask for devices again)."""
        if text not in self.notes:
            self.notes.append(text)


def _write_vendors(entries: dict[str, str]) -> Path:
    """A folder of ``.icd`` files (name -> library path), made once per content and
    written atomically (many processes may start at once)."""
    digest = hashlib.sha256(repr(sorted(entries.items())).encode()).hexdigest()[:16]
    for root in (cache_root() / "opencl", Path(tempfile.gettempdir()) / "skinpipe-opencl"):
        folder = root / f"vendors-{digest}"
        if folder.is_dir():
            return folder
        try:
            root.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=".vendors-", dir=root))
            for name, library in entries.items():
                (tmp / name).write_text(library + "\n")
            try:
                tmp.rename(folder)
            except OSError:  # another process made it first
                for f in tmp.iterdir():
                    f.unlink()
                tmp.rmdir()
            return folder
        except OSError:
            continue
    raise OSError("no writable folder for the OpenCL vendors list")


def register_runtimes() -> RuntimeSetup:
    """At import: the newer TBB loaded before pymeshlab's, PoCL's kernel cache folder,
    and what :func:`register_vendors` will need (Intel's library, whether the user set
    ``OCL_ICD_VENDORS``, which is left alone)."""
    setup = RuntimeSetup()
    settle_cache_root()  # before pyopencl keeps anything in the user's cache folder
    # PoCL compiles each kernel again at its first launch: keep those on disk too, in a
    # folder checked before PoCL reads it (a damaged kernel there kills the process)
    if not os.environ.get(POCL_CACHE_ENV):
        tree = GuardedTree(cache_root() / "pocl", "PoCL's kernels", ("last_accessed",))
        os.environ[POCL_CACHE_ENV] = str(tree.open())
        atexit.register(tree.close)
    intel = setup.intel = dist_file(INTEL_DIST, INTEL_LIBRARY)
    if intel is None:
        setup.notes.append("Intel CPU runtime: not installed (pip install "
                           "'skinpipe[intel-cpu]')")
    else:
        note = load_newer_tbb()
        if note is not None:
            setup.notes.append(f"Intel CPU runtime: {note}")
    if os.environ.get(ICD_ENV):
        setup.user_vendors = True
        setup.vendors = os.environ[ICD_ENV]
        if intel is not None and not any(
                Path(setup.vendors, f).is_file() and INTEL_LIBRARY in Path(
                    setup.vendors, f).read_text(errors="replace")
                for f in _listdir(setup.vendors)):
            setup.notes.append(f"Intel CPU runtime: {ICD_ENV} is set by you "
                               f"({setup.vendors}) and does not list {intel}")
    return setup


def register_vendors(with_intel: bool, setup: RuntimeSetup | None = None) -> None:
    """Before the loader's first platform query: point ``OCL_ICD_VENDORS`` at a folder
    with Intel's runtime and the machine's own entries if ``with_intel`` (and it is
    installed), else leave the loader to the machine's entries (and pyopencl's PoCL).
    Only the first call decides (the loader reads the variable once); a user's own
    ``OCL_ICD_VENDORS`` is left alone."""
    setup = SETUP if setup is None else setup
    if setup.settled:
        return
    setup.settled = True
    intel = setup.intel
    if setup.user_vendors or intel is None:
        return
    if not with_intel:
        setup.intel_left_out = True
        setup.notes.append("Intel CPU runtime: not loaded (PoCL passed skinpipe's probe on "
                           "this CPU before; --device intel or $SKINPIPE_OPENCL_DEVICE=intel "
                           "loads it)")
        return
    entries = {f.name: f.read_text(errors="replace").strip()
               for f in sorted(SYSTEM_VENDORS.glob("*.icd")) if f.is_file()} \
        if SYSTEM_VENDORS.is_dir() else {}
    entries["skinpipe-intel-cpu.icd"] = str(intel)
    try:
        folder = _write_vendors(entries)
    except OSError as exc:
        setup.notes.append(f"Intel CPU runtime: {exc}")
        return
    os.environ[ICD_ENV] = str(folder)
    setup.vendors = str(folder)


@lru_cache(maxsize=1)
def machine_key() -> str:
    """What decides whether PoCL builds here: the CPU (model and feature flags from
    ``/proc/cpuinfo``; its LLVM knows CPUs up to its own release) and pyopencl's PoCL
    (the library's name carries its build's hash)."""
    try:
        info = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        info = ""
    cpu = [ln.split(":", 1)[1].strip() for ln in info.splitlines()
           if ln.split(":", 1)[0].strip() in ("model name", "flags")][:2]
    try:
        spec = importlib.util.find_spec("pyopencl")
        libs = Path(spec.origin).parent / ".libs" if spec and spec.origin else None
        pocl = sorted(p.name for p in libs.glob("libpocl*")) if libs and libs.is_dir() else []
        version = metadata.version("pyopencl")
    except (metadata.PackageNotFoundError, OSError, ValueError):
        pocl, version = [], ""
    text = repr((cpu, pocl, version, sys.platform))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _pocl_record() -> Path:
    return cache_root() / "opencl" / f"pocl-passed-{machine_key()}"


def pocl_passed_here() -> bool:
    """Whether PoCL has passed skinpipe's probe on this CPU with this PoCL before."""
    try:
        return _pocl_record().is_file()
    except OSError:
        return False


def note_pocl_probe(passed: bool) -> None:
    """Keep (or drop) the record that PoCL passed the probe here; never fails."""
    try:
        record = _pocl_record()
        if passed:
            if not record.is_file():
                atomic_write_text(record, "passed\n")
        else:
            record.unlink(missing_ok=True)
    except OSError:
        pass


def _listdir(folder: str) -> list[str]:
    try:
        return os.listdir(folder)
    except OSError:
        return []


SETUP = register_runtimes()
"""Done once, when skinpipe is imported (``skinpipe/__init__.py`` imports this first)."""
