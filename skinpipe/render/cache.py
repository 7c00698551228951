"""Small results kept between processes in skinpipe's cache folder
(:func:`~.opencl_runtimes.cache_root`): JSON files named by a hash of everything that
made them (the library's version among it), so that a render need not import the
library that makes them. A file that does not read back, or whose content its reader
refuses, is made again; one that cannot be written is not kept (the result is the
same either way). Each kind's folder holds at most :data:`LIMIT_ENV` MB: past it, a
write removes the least recently used files (a read marks its file used)."""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
import os
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from ..errors import InputError
from ..fileio import atomic_write_text

T = TypeVar("T")


def cache_root() -> Path:
    """skinpipe's cache folder: ``$XDG_CACHE_HOME/skinpipe``, else ``~/.cache/skinpipe``
    (OpenCL vendors list, built programs, PoCL's kernels, the blur switch)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "skinpipe"

LIMIT_ENV = "SKINPIPE_KEPT_CACHE_MB"
"""Environment variable: the most one kind's folder of kept results may hold, in MB (10^6
bytes); :data:`DEFAULT_LIMIT_MB` where unset."""
DEFAULT_LIMIT_MB = 256.0
"""A mesh's UV charts, the largest kept result, take about 4 bytes a triangle (211 KB
for the demo face's 60 k triangles); the other kinds a few KB each."""
_STALE_TMP_S = 3600.0
"""A temporary file (``.name.*``, :func:`~skinpipe.fileio.atomic_path`) this old was left
by a killed process."""


def kept_path(kind: str, name: str, key: Any) -> Path:
    """The file that keeps a result of ``kind`` (a folder) made from ``key`` (anything
    JSON can write, which names every input), ``name`` its file name's prefix."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:32]
    return cache_root() / kind / f"{name}-{digest}.json"


def read_kept(path: Path) -> dict[str, Any] | None:
    """The object kept at ``path``, or None where there is none that reads back."""
    with contextlib.suppress(OSError, ValueError):
        doc = json.loads(path.read_text())
        if isinstance(doc, dict):
            with contextlib.suppress(OSError):
                os.utime(path)  # most recently used: the last to go
            return doc
    return None


def keep(path: Path, doc: dict[str, Any]) -> None:
    """Keep ``doc`` at ``path`` (atomically, compact JSON: a mesh's charts are a number a
    triangle), or nothing where it cannot be written."""
    limit = limit_bytes()  # a bad limit is the user's to hear of, not a file not kept
    with contextlib.suppress(OSError, ValueError):
        atomic_write_text(path, json.dumps(doc, separators=(",", ":"), allow_nan=False))
        evict(path.parent, limit, keep=path)


def limit_bytes() -> float:
    """The most a kind's folder may hold, in bytes (:data:`LIMIT_ENV`); a value that is
    not a number >= 0 is refused with the variable named."""
    raw = os.environ.get(LIMIT_ENV, "").strip()
    if not raw:
        return DEFAULT_LIMIT_MB * 1e6
    try:
        mb = float(raw)
    except ValueError:
        mb = -1.0
    if not mb >= 0:  # NaN too
        raise InputError(f"${LIMIT_ENV} must be a number of MB >= 0, got {raw!r}")
    return mb * 1e6


def evict(folder: Path, limit: float, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used files of ``folder`` (by modification time, which
    :func:`read_kept` renews) while it holds more than ``limit`` bytes, never ``keep``
    nor a temporary file being written, and temporary files a killed process left; the
    files removed. Files another user owns in a shared folder stay."""
    now = time.time()
    files = []
    with contextlib.suppress(OSError):
        for entry in os.scandir(folder):
            with contextlib.suppress(OSError):
                st = entry.stat(follow_symlinks=False)
                if not entry.is_file(follow_symlinks=False):
                    continue
                if entry.name.startswith("."):  # a temporary file: being written, or
                    if now - st.st_mtime > _STALE_TMP_S:  # left by a killed process
                        os.unlink(entry.path)
                    continue
                files.append((st.st_mtime, st.st_size, Path(entry.path)))
    total = sum(size for _, size, _ in files)
    removed = []
    for _, size, path in sorted(files, key=lambda f: f[0]):
        if total <= limit:
            break
        if keep is not None and path == keep:
            continue
        with contextlib.suppress(OSError):
            path.unlink()
            total -= size
            removed.append(path)
    return removed


def kept(kind: str, name: str, key: Any, read: Callable[[dict[str, Any]], T],
         make: Callable[[], tuple[T, dict[str, Any]]]) -> T:
    """The result of ``key`` (anything JSON can write, which names every input):
    ``read(doc)`` of the object kept with that key where one reads back and ``read``
    takes it (it raises ValueError, KeyError or TypeError to refuse it), else the result
    of ``make()``, which also gives the object to keep (what ``read`` takes back)."""
    path = kept_path(kind, name, key)
    doc = read_kept(path)
    if doc is not None and doc.get("key") == key:
        with contextlib.suppress(ValueError, KeyError, TypeError):
            return read(doc)
    result, made = make()
    keep(path, {**made, "key": key})
    return result


@lru_cache(maxsize=64)
def source_of(*functions: Callable[..., Any]) -> str:
    """A hash of the functions' source, for a key: a result kept by other code (an
    edited function) is not read back. Once per process (3-7 ms a render)."""
    h = hashlib.blake2b(digest_size=16)
    for function in functions:
        h.update(inspect.getsource(function).encode())
    return h.hexdigest()
