"""Atomic file output: write to a temporary sibling, fsync, then rename.

Readers (a farm job, a re-run of a batch) must never see a half-written file, and a
failed write must not truncate the previous good one. ``os.replace`` is atomic on
POSIX within one file system, hence the temporary file lives beside the target.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def atomic_path(target: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``target``; on success fsync it and rename it over.

    The temporary name keeps the target's suffix (``suffix`` overrides it) because
    OpenImageIO and USD choose the file format from the extension. On an exception the
    temporary file is removed and ``target`` is left untouched.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(
        prefix=f".{target.stem}.", suffix=suffix if suffix is not None else target.suffix,
        dir=target.parent,
    )
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise OSError(f"{target}: nothing was written")
        with open(tmp, "rb+") as handle:
            os.fsync(handle.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, target)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()


def atomic_write_text(target: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``target`` atomically and return the target path."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


def atomic_write_json(target: str | Path, data: Any) -> Path:
    """Write ``data`` as indented JSON atomically (NaN is refused: JSON has none)."""
    return atomic_write_text(target, json.dumps(data, indent=2, allow_nan=False) + "\n")


@contextlib.contextmanager
def atomic_directory(target: str | Path) -> Iterator[Path]:
    """Yield a temporary directory beside ``target``; on success it replaces ``target``.

    A directory of outputs (a batch stage's) appears whole or not at all: a killed
    process leaves only a ``.name.tmp-*`` sibling, which no reader trusts. An existing
    ``target`` is moved aside first and removed after the new one is in place.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.tmp-", dir=target.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o755)  # mkdtemp's 0700 would hide the outputs from other users
        old = None
        if target.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{target.name}.old-", dir=target.parent))
            os.replace(target, old / target.name)
        os.replace(tmp, target)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)


def stale_siblings(target: str | Path) -> list[Path]:
    """Temporaries that :func:`atomic_directory` left beside ``target`` when its process
    was killed (``.name.tmp-*``, ``.name.old-*``)."""
    target = Path(target)
    if not target.parent.is_dir():
        return []
    return sorted(p for p in target.parent.iterdir()
                  if p.name.startswith((f".{target.name}.tmp-", f".{target.name}.old-")))


def relocate_paths(doc: Any, old: str, new: str) -> Any:
    """``doc`` (JSON data) with every string that starts with the path ``old`` pointing
    under ``new`` instead: records written in a temporary directory name their final
    place."""
    if isinstance(doc, str):
        return new + doc[len(old):] if doc == old or doc.startswith(old + os.sep) else doc
    if isinstance(doc, list):
        return [relocate_paths(v, old, new) for v in doc]
    if isinstance(doc, dict):
        return {k: relocate_paths(v, old, new) for k, v in doc.items()}
    return doc
