"""What a PLY or OBJ file says it holds, read by skinpipe itself, and pymeshlab's reader
run where a crash becomes an error.

pymeshlab's readers kill the interpreter on some bad face lines (``f 1 2 -999999``:
SIGSEGV), and repair others silently: NaN/inf vertices are dropped with their faces,
out-of-range and zero-area faces dropped, unparseable vertex lines read as (0, 0, 0).
So the file is scanned first (:func:`scan_mesh_file`: counts, finiteness, index range,
with the line or element at fault), pymeshlab reads it in a child process
(:func:`load_in_child`), and what it read is compared with what the file declares.
"""

from __future__ import annotations

import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..children import child_failure, python_command
from ..errors import InputError

MAX_MESH_BYTES = 2 * 1024**3
"""Larger mesh files are refused (a face scan is tens of MB)."""
LOAD_TIMEOUT_S = 300.0
_CHILD = Path(__file__).with_name("_meshlab_child.py")


@dataclass(frozen=True)
class MeshFileFacts:
    """Vertex count and triangle count (polygons fanned) that a file declares."""

    vertices: int
    triangles: int
    low: tuple[float, float, float] | None = None
    high: tuple[float, float, float] | None = None
    """The vertices' bounding box, where the scan read them."""


def scan_mesh_file(path: Path) -> MeshFileFacts:
    """Check a PLY or OBJ file before any library reads it; InputError naming the line
    (OBJ, ASCII PLY) or the element (binary PLY) at fault."""
    size = path.stat().st_size
    if size == 0:
        raise InputError("empty mesh file", path)
    if size > MAX_MESH_BYTES:
        raise InputError(f"mesh file of {size / 1024**3:.1f} GiB (limit "
                         f"{MAX_MESH_BYTES / 1024**3:.0f} GiB)", path)
    if path.suffix.lower() == ".obj":
        return _scan_obj(path)
    return _scan_ply(path)


def _scan_obj(path: Path) -> MeshFileFacts:
    n_vertices = 0
    triangles = 0
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    with open(path, "rb") as handle:
        for number, raw in enumerate(handle, start=1):
            line = raw.split(b"#", 1)[0].strip()
            if line.startswith(b"v "):
                try:
                    xyz = [float(t) for t in line.split()[1:4]]
                except ValueError:
                    xyz = []
                if len(xyz) != 3 or not all(np.isfinite(xyz)):
                    raise InputError(f"line {number}: a vertex needs 3 finite numbers, got "
                                     f"{raw.strip()[:80].decode(errors='replace')!r}", path)
                n_vertices += 1
                low, high = np.minimum(low, xyz), np.maximum(high, xyz)
            elif line.startswith(b"f "):
                refs = line.split()[1:]
                if len(refs) < 3:
                    raise InputError(f"line {number}: a face needs at least 3 vertices", path)
                seen = set()
                for ref in refs:
                    try:
                        index = int(ref.split(b"/", 1)[0])
                    except ValueError:
                        index = 0
                    # OBJ indices are 1-based; negative ones count back from the last vertex
                    resolved = index - 1 if index > 0 else n_vertices + index
                    if index == 0 or not 0 <= resolved < n_vertices:
                        raise InputError(
                            f"line {number}: face vertex {ref.decode(errors='replace')!r} "
                            f"is not one of the {n_vertices} vertices defined before it", path)
                    if resolved in seen:
                        raise InputError(f"line {number}: the face repeats vertex "
                                         f"{ref.decode(errors='replace')!r} (no area)", path)
                    seen.add(resolved)
                triangles += len(refs) - 2
    if n_vertices == 0 or triangles == 0:
        raise InputError(f"no {'vertices' if n_vertices == 0 else 'faces'} in the OBJ file",
                         path)
    return MeshFileFacts(n_vertices, triangles, tuple(low), tuple(high))


_PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2",
              "int16": "i2", "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4",
              "uint": "u4", "uint32": "u4", "float": "f4", "float32": "f4", "double": "f8",
              "float64": "f8"}


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, type, list count type)


def _ply_header(path: Path) -> tuple[str, list[_Element], int]:
    with open(path, "rb") as handle:
        head = handle.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise InputError("not a PLY file (no 'ply' ... 'end_header' header)", path)
    newline = head.find(b"\n", end)
    body_start = newline + 1 if newline >= 0 else len(head)
    fmt = ""
    elements: list[_Element] = []
    for number, raw in enumerate(head[:end].decode("ascii", "replace").splitlines(), 1):
        words = raw.split()
        if not words or words[0] in ("ply", "comment", "obj_info"):
            continue
        try:
            if words[0] == "format":
                fmt = words[1]
            elif words[0] == "element":
                elements.append(_Element(words[1], int(words[2]), []))
            elif words[0] == "property" and words[1] == "list":
                elements[-1].properties.append((words[4], _PLY_TYPES[words[3]],
                                                _PLY_TYPES[words[2]]))
            elif words[0] == "property":
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]], None))
        except (IndexError, KeyError, ValueError):
            raise InputError(f"header line {number}: cannot read {raw!r}", path) from None
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format {fmt!r}", path)
    if any(e.count < 0 for e in elements):
        raise InputError("negative element count in the header", path)
    return fmt, elements, body_start


def _scan_ply(path: Path) -> MeshFileFacts:
    fmt, elements, start = _ply_header(path)
    names = [e.name for e in elements]
    if "vertex" not in names or "face" not in names:
        raise InputError(f"a PLY mesh needs vertex and face elements, the header has {names}",
                         path)
    vertex = elements[names.index("vertex")]
    if not {"x", "y", "z"} <= {p[0] for p in vertex.properties if p[2] is None}:
        raise InputError("the vertex element has no x, y, z properties", path)
    data = path.read_bytes()[start:]
    if fmt == "ascii":
        return _scan_ply_ascii(path, data, elements, start)
    order = "<" if fmt == "binary_little_endian" else ">"
    offset = 0
    triangles = 0
    box: tuple[Any, Any] = (None, None)
    for element in elements:
        scalar = all(p[2] is None for p in element.properties)
        if scalar:
            dtype = np.dtype([(n, order + t) for n, t, _ in element.properties])
            need = dtype.itemsize * element.count
            if offset + need > len(data):
                raise InputError(f"the file ends inside its {element.name} element "
                                 f"({element.count} declared)", path)
            values = np.frombuffer(data, dtype, element.count, offset)
            offset += need
            if element.name == "vertex":
                xyz = np.stack([values[c].astype(np.float64) for c in "xyz"], axis=1)
                _check_vertices(path, xyz, "vertex")
                box = (tuple(xyz.min(axis=0)), tuple(xyz.max(axis=0)))
            continue
        if element.name != "face":
            raise InputError(f"element {element.name!r} with list properties before the "
                             "faces: skinpipe cannot check it", path)
        triangles, offset = _scan_binary_faces(path, data, offset, element, order,
                                               vertex.count)
    return MeshFileFacts(vertex.count, triangles, *box)


def _scan_binary_faces(path: Path, data: bytes, offset: int, element: _Element,
                       order: str, n_vertices: int) -> tuple[int, int]:
    """Check every index of a binary face element: vectorised when every face has as
    many vertices as the first (a triangle scan), walked face by face otherwise."""
    uniform = _uniform_faces(data, offset, element, order, n_vertices, path)
    if uniform is not None:
        return uniform
    triangles = 0
    for i in range(element.count):
        for name, kind, count_kind in element.properties:
            if count_kind is None:
                offset += np.dtype(kind).itemsize
                continue
            if offset + np.dtype(count_kind).itemsize > len(data):
                raise InputError(f"the file ends inside face {i}", path)
            n = int(np.frombuffer(data, order + count_kind, 1, offset)[0])
            offset += np.dtype(count_kind).itemsize
            size = np.dtype(kind).itemsize * n
            if offset + size > len(data):
                raise InputError(f"the file ends inside face {i}", path)
            indices = np.frombuffer(data, order + kind, n, offset)
            offset += size
            if name in ("vertex_indices", "vertex_index"):
                if n < 3:
                    raise InputError(f"face {i} has {n} vertices", path)
                if indices.min() < 0 or indices.max() >= n_vertices:
                    raise InputError(f"face {i}: vertex index {int(indices.max())} outside "
                                     f"0..{n_vertices - 1}", path)
                triangles += n - 2
    return triangles, offset


def _uniform_faces(data: bytes, offset: int, element: _Element, order: str,
                   n_vertices: int, path: Path) -> tuple[int, int] | None:
    first_list = next(p for p in element.properties if p[2] is not None)
    lead = sum(np.dtype(k).itemsize for _, k, c in element.properties[
        :element.properties.index(first_list)])
    if offset + lead + 1 > len(data):
        raise InputError("the file ends inside the face element", path)
    n = int(np.frombuffer(data, order + first_list[2], 1, offset + lead)[0])
    fields = []
    for name, kind, count_kind in element.properties:
        if count_kind is None:
            fields.append((name, order + kind))
        else:
            fields += [(f"{name}#n", order + count_kind), (name, order + kind, (n,))]
    dtype = np.dtype(fields)
    if n < 3 or offset + dtype.itemsize * element.count > len(data):
        return None
    faces = np.frombuffer(data, dtype, element.count, offset)
    if any(np.any(faces[f"{name}#n"] != n) for name, _, c in element.properties if c):
        return None
    key = next((k for k in ("vertex_indices", "vertex_index") if k in dtype.names), None)
    if key is not None:
        idx = faces[key]
        bad = (idx < 0).any(axis=1) | (idx >= n_vertices).any(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"face {i}: vertex index outside 0..{n_vertices - 1} "
                             f"({idx[i].tolist()})", path)
        srt = np.sort(idx, axis=1)
        repeated = (srt[:, 1:] == srt[:, :-1]).any(axis=1)
        if repeated.any():
            i = int(np.flatnonzero(repeated)[0])
            raise InputError(f"face {i} repeats a vertex ({idx[i].tolist()}): no area", path)
    return element.count * (n - 2), offset + dtype.itemsize * element.count


def _scan_ply_ascii(path: Path, data: bytes, elements: list[_Element],
                    start: int) -> MeshFileFacts:
    lines = data.decode("ascii", "replace").splitlines()
    first = path.read_bytes()[:start].count(b"\n") + 1  # the body's first line number
    row = 0
    triangles = 0
    low, high = np.full(3, np.inf), np.full(3, -np.inf)
    n_vertices = next(e.count for e in elements if e.name == "vertex")
    for element in elements:
        for i in range(element.count):
            if row >= len(lines):
                raise InputError(f"the file ends inside its {element.name} element "
                                 f"({element.count} declared, {i} read)", path)
            words = lines[row].split()
            where = f"line {first + row}"
            row += 1
            try:
                values = [float(w) for w in words]
            except ValueError:
                raise InputError(f"{where}: cannot read {lines[row - 1][:80]!r}", path) from None
            if element.name == "vertex":
                names = [p[0] for p in element.properties]
                if len(values) < len(names):
                    raise InputError(f"{where}: {len(values)} values for {len(names)} "
                                     "properties", path)
                xyz = np.array([[values[names.index(c)] for c in "xyz"]])
                _check_vertices(path, xyz, where)
                low, high = np.minimum(low, xyz[0]), np.maximum(high, xyz[0])
            elif element.name == "face" and values:
                n = int(values[0])
                idx = np.asarray(values[1:1 + n])
                if n < 3 or idx.size != n:
                    raise InputError(f"{where}: a face needs at least 3 vertex indices", path)
                if idx.min() < 0 or idx.max() >= n_vertices or np.any(idx != np.round(idx)):
                    raise InputError(f"{where}: vertex index outside 0..{n_vertices - 1}",
                                     path)
                if np.unique(idx).size < n:
                    raise InputError(f"{where}: the face repeats a vertex (no area)", path)
                triangles += n - 2
    return MeshFileFacts(n_vertices, triangles, tuple(low), tuple(high))


def _check_vertices(path: Path, xyz: np.ndarray, where: str) -> None:
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        label = f"vertex {first}" if where == "vertex" else where
        raise InputError(f"{label}: non-finite position {xyz[first].tolist()} "
                         f"({int(bad.sum())} such vertices)", path)


def load_in_child(path: Path, facts: MeshFileFacts, timeout_s: float = LOAD_TIMEOUT_S
                  ) -> dict[str, np.ndarray]:
    """pymeshlab's reader in a child process: points, triangles and (if any) per-vertex
    texture coordinates. A crash or a timeout there is an InputError here, and so is a
    mesh that differs from what the file declares (pymeshlab dropped or repaired
    something)."""
    with tempfile.TemporaryDirectory(prefix="skinpipe-mesh-") as tmp:
        out = Path(tmp) / "mesh.npz"
        try:
            proc = subprocess.run(python_command(str(_CHILD), str(path), str(out)),
                                  capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise InputError(f"pymeshlab did not read it in {timeout_s:.0f} s", path) from None
        if proc.returncode != 0 or not out.is_file():
            why = child_failure("pymeshlab's reader", proc.returncode, proc.stderr,
                                "skinpipe-meshlab-error:")
            raise InputError(f"cannot load mesh: {why}", path)
        with np.load(out) as npz:
            arrays = {k: npz[k] for k in npz.files}
    n_points, n_faces = arrays["points"].shape[0], arrays["faces"].shape[0]
    if (n_points, n_faces) != (facts.vertices, facts.triangles):
        raise InputError(f"the file declares {facts.vertices} vertices and {facts.triangles} "
                         f"triangles but pymeshlab read {n_points} and {n_faces} (it drops "
                         "degenerate, duplicate or unreadable elements): repair the file",
                         path)
    if facts.low is not None and n_points:
        low, high = arrays["points"].min(axis=0), arrays["points"].max(axis=0)
        scale = max(float(np.abs(np.r_[facts.low, facts.high]).max()), 1e-30)
        if not (np.allclose(low, facts.low, rtol=0, atol=1e-5 * scale) and
                np.allclose(high, facts.high, rtol=0, atol=1e-5 * scale)):
            raise InputError(f"the file's vertices span {list(facts.low)} to "
                             f"{list(facts.high)} but pymeshlab read {low.tolist()} to "
                             f"{high.tolist()}: repair the file", path)
    return arrays
