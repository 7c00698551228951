"""Guarded USD reads and atomic USD writes.

USD's text parser crashes the interpreter on lists or dictionaries nested tens of
thousands deep and takes minutes on deep tuples; a .usdc saved over an existing file is
rewritten in place. Every layer a stage will compose (the file named, its sublayers,
references and payloads, recursively, and the text layers inside a .usdz) is therefore
checked before USD parses it, and layers are exported to a temporary sibling, fsynced
and renamed.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Sdf, Tf, Usd, UsdUtils

from ..errors import InputError
from ..fileio import atomic_path

MAX_USDA_NESTING = 256
USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
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


def _check_usda_text(data: bytes, where: str | Path) -> None:
    depth = usda_nesting_depth(data)
    if depth > MAX_USDA_NESTING:
        raise InputError(f".usda text nested {depth} deep (limit {MAX_USDA_NESTING}): "
                         "refusing to parse it (USD's parser crashes on such files)", where)
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f".usda text is not UTF-8 (byte {exc.start}: "
                         f"{data[exc.start:exc.start + 1]!r})", where) from exc


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
        _check_usda_text(path.read_bytes(), path)
    elif head.startswith(b"PK"):
        try:
            with zipfile.ZipFile(path) as package:
                for member in package.namelist():
                    if member.lower().endswith((".usd", ".usda")):
                        data = package.read(member)
                        if data.startswith(b"#usda"):
                            _check_usda_text(data, f"{path}[{member}]")
        except (zipfile.BadZipFile, OSError) as exc:
            raise InputError(f"not a readable .usdz package: {exc}", path) from exc
    elif not head.startswith(b"PXR-USDC"):
        raise InputError("not a USD file (neither usda text, usdc crate nor usdz)", path)
    return path


def composed_layer_files(path: str | Path) -> list[Path]:
    """Every layer file that opening ``path`` composes (sublayers, references, payloads,
    recursively), each checked by :func:`check_usd_file` before USD parses it; the root
    first. Layers inside a .usdz were checked with their package."""
    root = check_usd_file(path).absolute()
    seen: dict[Path, None] = {}
    todo = [root]
    while todo:
        file = todo.pop()
        if file in seen:
            continue
        if file != root:  # the root was checked above, under the name it was given
            check_usd_file(file)
        seen[file] = None
        if file.suffix.lower() == ".usdz":
            continue
        layer = _open_layer(file)
        for dep in layer.GetCompositionAssetDependencies():
            resolved = Path(layer.ComputeAbsolutePath(dep)) if dep else None
            if resolved is not None and resolved.is_file():
                todo.append(resolved.absolute())
    return list(seen)


_TF_ERROR = re.compile(
    r"Error in '[^']*' at line \d+ in file \S+ : '(.*?)'\s*(?=\n\s*Error in '|\Z)", re.S)
_PXR_NAMESPACE = re.compile(r"pxrInternal_v[0-9_]+__pxrReserved__::")


def usd_error_message(exc: Exception) -> str:
    """The reason in a Tf error (for a parse error USD's own file:line:column message),
    without the location in USD's sources. A reason may span lines."""
    text = str(exc).strip()
    if not text:
        return type(exc).__name__
    errors = [m.group(1).strip() for m in _TF_ERROR.finditer(text)] or [text.splitlines()[-1]]
    return _PXR_NAMESPACE.sub("", "; ".join(e for e in errors if e) or text)


def _open_layer(file: Path) -> Any:
    try:
        layer = Sdf.Layer.FindOrOpen(str(file))
    except Tf.ErrorException as exc:
        raise InputError(f"USD cannot read it: {usd_error_message(exc)}", file) from exc
    if layer is None:
        raise InputError("USD cannot read it", file)
    return layer


def usd_inputs(path: str | Path) -> list[Path]:
    """The files a command that opens ``path`` reads: its layers (checked as by
    :func:`composed_layer_files`) and the assets they name (textures, MaterialX files)."""
    layers = composed_layer_files(path)
    _, assets, _ = UsdUtils.ComputeAllDependencies(str(layers[0]))
    return layers + [Path(a) for a in assets if a and "[" not in a and Path(a).is_file()]


def open_stage_guarded(path: str | Path) -> Any:
    """Open a stage read-only after checking every layer it composes
    (:func:`composed_layer_files`); InputError if USD refuses it."""
    path = Path(path)
    composed_layer_files(path)
    try:
        stage = Usd.Stage.Open(str(path), Usd.Stage.LoadAll)
    except Tf.ErrorException as exc:
        raise InputError(f"USD cannot open it: {usd_error_message(exc)}", path) from exc
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
