"""Guarded USD reads and atomic USD writes.

USD's text parser crashes the interpreter on lists or dictionaries nested tens of
thousands deep and takes minutes on deep tuples; a .usdc saved over an existing file is
rewritten in place. Files from outside are therefore checked before they are opened,
and layers are exported to a temporary sibling, fsynced and renamed.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Tf, Usd

from ..errors import InputError
from ..fileio import atomic_path

MAX_USDA_NESTING = 256
_STRINGS = re.compile(rb'"""(?:.|\n)*?"""|\'\'\'(?:.|\n)*?\'\'\'|"(?:\\.|[^"\\\n])*"|'
                      rb"'(?:\\.|[^'\\\n])*'|#[^\n]*")


def usda_nesting_depth(data: bytes) -> int:
    """Deepest bracket nesting ([, (, {) of .usda text, strings and comments ignored."""
    stripped = _STRINGS.sub(b"", data)
    arr = np.frombuffer(stripped, dtype=np.uint8)
    step = np.zeros(arr.size, dtype=np.int32)
    for ch in b"[({":
        step[arr == ch] = 1
    for ch in b"])}":
        step[arr == ch] = -1
    return int(np.cumsum(step).max(initial=0))


def check_usd_file(path: str | Path) -> Path:
    """Refuse files that would crash or stall USD's parser; return the path."""
    path = Path(path)
    if not path.is_file():
        raise InputError("no such USD file", path)
    if path.stat().st_size == 0:
        raise InputError("empty USD file", path)
    with open(path, "rb") as handle:
        head = handle.read(8)
    if head.startswith(b"#usda"):
        depth = usda_nesting_depth(path.read_bytes())
        if depth > MAX_USDA_NESTING:
            raise InputError(f".usda text nested {depth} deep (limit {MAX_USDA_NESTING}): "
                             "refusing to parse it (USD's parser crashes on such files)", path)
    elif not head.startswith(b"PXR-USDC") and not head.startswith(b"PK"):
        raise InputError("not a USD file (neither usda text, usdc crate nor usdz)", path)
    return path


def open_stage_guarded(path: str | Path) -> Any:
    """Open a stage read-only after :func:`check_usd_file`; InputError if USD refuses it."""
    path = check_usd_file(path)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise InputError(f"USD cannot open it: {str(exc).strip().splitlines()[-1]}", path) \
            from exc
    if stage is None:
        raise InputError("USD cannot open it", path)
    return stage


def export_layer_atomic(layer: Any, target: str | Path) -> Path:
    """Export an Sdf layer to ``target`` through a temporary sibling of the same format."""
    target = Path(target)
    with atomic_path(target) as tmp:
        if not layer.Export(str(tmp)):
            raise OSError(f"{target}: USD could not export the layer")
    return target
