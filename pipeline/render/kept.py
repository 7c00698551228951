"""Small results kept between processes in skinpipe's cache folder
(:func:`~.opencl_runtimes.cache_root`): JSON files named by a hash of everything that
made them (the library's version among it), so that a render need not import the
library that makes them. A file that does not read back, or whose content its reader
refuses, is made again; one that cannot be written is not kept (the result is the
same either way)."""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

from ..fileio import atomic_write_text
from .opencl_runtimes import cache_root

T = TypeVar("T")


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
            return doc
    return None


def keep(path: Path, doc: dict[str, Any]) -> None:
    """Keep ``doc`` at ``path`` (atomically, compact JSON: a mesh's charts are a number a
    triangle), or nothing where it cannot be written."""
    with contextlib.suppress(OSError, ValueError):
        atomic_write_text(path, json.dumps(doc, separators=(",", ":"), allow_nan=False))


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
