"""Meshes at the stage boundary: load (USD, PLY, OBJ), validate, clean up a raw scan.

Embree and xatlas misbehave silently or hang on non-finite or huge coordinates and on
bad indices, so every mesh is validated here before any later stage sees it.
"""

from __future__ import annotations

import subprocess
import tempfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pxr import Usd, UsdGeom

from ..children import child_failure, python_command
from ..errors import InputError
from ..native import import_pymeshlab, pymeshlab_folder
from .io import USD_SUFFIXES, open_stage_guarded
from .mesh_files import load_in_child, scan_mesh_file

MAX_COORDINATE = 1e7  # in scene units; beyond this a mesh is treated as corrupt


@dataclass(frozen=True)
class MeshData:
    """A polygon mesh: points (N, 3), per-face vertex counts (F,), flat vertex indices.

    ``st`` is a per-vertex texture coordinate (N, 2) if the source had one;
    ``meters_per_unit`` says what one unit of ``points`` is.
    """

    points: NDArray[np.float64]
    face_counts: NDArray[np.int32]
    face_indices: NDArray[np.int32]
    meters_per_unit: float
    st: NDArray[np.float64] | None = None
    source: Path | None = None

    @property
    def n_faces(self) -> int:
        return int(self.face_counts.size)

    def face_vertex_lists(self) -> list[NDArray[np.int32]]:
        return np.split(self.face_indices, np.cumsum(self.face_counts)[:-1])

    def face_centroids(self) -> NDArray[np.float64]:
        starts = np.concatenate([[0], np.cumsum(self.face_counts)[:-1]])
        sums = np.add.reduceat(self.points[self.face_indices], starts, axis=0)
        return sums / self.face_counts[:, None]


def validate_mesh(mesh: MeshData) -> MeshData:
    """Raise InputError (naming the source) for a mesh no later stage can use safely."""
    src = mesh.source
    pts = mesh.points
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise InputError(f"mesh points must be a non-empty (N, 3) array, got {pts.shape}", src)
    finite = np.isfinite(pts).all(axis=1)
    if not finite.all():
        bad = int(np.flatnonzero(~finite)[0])
        raise InputError(f"{int((~finite).sum())} non-finite vertex position(s), first at "
                         f"vertex {bad}: {pts[bad].tolist()}", src)
    if not np.ptp(pts, axis=0).max() > 0:
        raise InputError(f"all {pts.shape[0]} vertices are at one point {pts[0].tolist()}", src)
    if np.abs(pts).max() > MAX_COORDINATE:
        raise InputError(f"vertex coordinates up to {np.abs(pts).max():.3g} scene units: "
                         "corrupt or in the wrong unit", src)
    if mesh.face_counts.size == 0:
        raise InputError("the mesh has no faces", src)
    if np.any(mesh.face_counts < 3):
        raise InputError("faces with fewer than 3 vertices", src)
    if int(mesh.face_counts.sum()) != mesh.face_indices.size:
        raise InputError(f"face vertex counts sum to {int(mesh.face_counts.sum())} but there "
                         f"are {mesh.face_indices.size} indices", src)
    if mesh.face_indices.min() < 0 or mesh.face_indices.max() >= pts.shape[0]:
        raise InputError(f"face vertex indices outside 0..{pts.shape[0] - 1}", src)
    if not mesh.meters_per_unit > 0:
        raise InputError(f"metersPerUnit must be > 0, got {mesh.meters_per_unit}", src)
    return mesh


def load_mesh(path: str | Path, meters_per_unit: float | None = None,
              prim_path: str | None = None) -> MeshData:
    """Load a mesh from USD (the first Mesh, or ``prim_path``), PLY or OBJ (pymeshlab).

    Scene units: a USD stage's metersPerUnit; for PLY/OBJ ``meters_per_unit`` (default
    0.001, millimetres, the unit of range scans). The source file is only read.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("no such mesh file", path)
    suffix = path.suffix.lower()
    if suffix in USD_SUFFIXES:
        mesh = _load_usd_mesh(path, prim_path, meters_per_unit)
    elif suffix in (".ply", ".obj"):
        mesh = _load_meshlab(path, 0.001 if meters_per_unit is None else meters_per_unit)
    else:
        raise InputError(f"unsupported mesh type {suffix!r} (USD, PLY or OBJ)", path)
    return validate_mesh(mesh)


def _load_meshlab(path: Path, meters_per_unit: float) -> MeshData:
    facts = scan_mesh_file(path)
    arrays = load_in_child(path, facts)
    faces = arrays["faces"]
    return MeshData(arrays["points"], np.full(faces.shape[0], 3, np.int32), faces.reshape(-1),
                    meters_per_unit, arrays.get("st"), path)


def _load_usd_mesh(path: Path, prim_path: str | None, meters_per_unit: float | None) -> MeshData:
    stage = open_stage_guarded(path)
    if prim_path:
        prim = stage.GetPrimAtPath(prim_path)
        if not prim or not prim.IsA(UsdGeom.Mesh):
            raise InputError(f"no Mesh at {prim_path}", path)
    else:
        prim = next((p for p in Usd.PrimRange(stage.GetPseudoRoot()) if p.IsA(UsdGeom.Mesh)),
                    None)
        if prim is None:
            raise InputError("no Mesh prim in the stage", path)
    mesh = UsdGeom.Mesh(prim)
    points = mesh.GetPointsAttr().Get()
    counts = mesh.GetFaceVertexCountsAttr().Get()
    indices = mesh.GetFaceVertexIndicesAttr().Get()
    if points is None or counts is None or indices is None:
        raise InputError(f"{prim.GetPath()}: points or topology not authored", path)
    xform = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(
        Usd.TimeCode.Default()), dtype=np.float64)
    pts = np.asarray(points, dtype=np.float64)
    pts = pts @ xform[:3, :3] + xform[3, :3]
    st = None
    pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar("st")
    if pv and pv.HasValue() and pv.GetInterpolation() in (UsdGeom.Tokens.vertex,
                                                           UsdGeom.Tokens.varying):
        st = np.asarray(pv.ComputeFlattened(), dtype=np.float64)
    mpu = meters_per_unit if meters_per_unit is not None else UsdGeom.GetStageMetersPerUnit(stage)
    return MeshData(pts, np.asarray(counts, np.int32), np.asarray(indices, np.int32), mpu, st,
                    path)


def prepare_scan(mesh: MeshData, target_faces: int = 60000, max_hole_edges: int = 300,
                 min_component_fraction: float = 0.01) -> MeshData:
    """Clean a raw range scan with pymeshlab: merge duplicates, drop degenerate faces and
    every piece but the largest, close the holes inside the scan (up to
    ``max_hole_edges`` boundary edges), decimate to ``target_faces`` (quadric edge
    collapse). The scan's outer rim stays open: :func:`seal_scan` closes it."""
    pymeshlab = import_pymeshlab()

    if np.any(mesh.face_counts != 3):
        raise InputError("prepare_scan needs a triangle mesh", mesh.source)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.points,
                               face_matrix=mesh.face_indices.reshape(-1, 3)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_remove_connected_component_by_diameter(
        mincomponentdiag=pymeshlab.PercentageValue(100 * min_component_fraction * 10))
    ms.meshing_remove_unreferenced_vertices()
    # hole closing skips holes that touch a non-manifold vertex: repair those first
    # (on the face scan this takes the interior gaps from "not closable" to closed)
    for _ in range(3):
        ms.meshing_repair_non_manifold_edges()
        ms.meshing_repair_non_manifold_vertices()
    ms.meshing_remove_unreferenced_vertices()
    # a detached piece (the face scan has a strip of the side of the head 10 mm off the
    # face) leaves a slit that no hole filling closes: keep the largest piece only
    ms.meshing_remove_connected_component_by_face_number(
        mincomponentsize=_largest_component_faces(ms.current_mesh().face_matrix()))
    ms.meshing_remove_unreferenced_vertices()
    # the self-intersection check refuses the wide gaps a range scan leaves (cap, side of
    # the head): they would stay open and let light through, so it is off
    ms.meshing_close_holes(maxholesize=max_hole_edges, selfintersection=False)
    # A selection left by an earlier filter makes quadric decimation a silent no-op.
    ms.set_selection_none()
    if ms.current_mesh().face_number() > target_faces:
        ms.meshing_decimation_quadric_edge_collapse(
            targetfacenum=target_faces, preservenormal=True, planarquadric=True,
            preserveboundary=True, preservetopology=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    faces = np.asarray(m.face_matrix(), dtype=np.int32)
    return validate_mesh(replace(mesh, points=np.asarray(m.vertex_matrix(), dtype=np.float64),
                                 face_counts=np.full(faces.shape[0], 3, np.int32),
                                 face_indices=faces.reshape(-1), st=None))


def _largest_component_faces(faces: NDArray[Any]) -> int:
    """Face count of the largest edge-connected piece of a triangle mesh."""
    import scipy.sparse as sp  # lazy: with csgraph, 0.27 s to import
    from scipy.sparse.csgraph import connected_components  # lazy: 0.27 s to import

    n = int(faces.max()) + 1
    adj = sp.coo_matrix((np.ones(faces.size), (np.repeat(faces[:, 0], 3), faces.reshape(-1))),
                        shape=(n, n))
    _, label = connected_components(adj, directed=False)
    return int(np.bincount(label[faces[:, 0]]).max())


def seal_scan(mesh: MeshData) -> MeshData | None:
    """The faces that close every boundary left in ``mesh`` (a range scan's open rim:
    the back of the head the scanner never saw), over ``mesh``'s points, compacted.

    The skin keeps its texture space; the seal is a separate occluder so that no shadow
    or camera ray passes through the scan. ``None`` when the mesh is already closed."""
    pymeshlab = import_pymeshlab()

    faces = mesh.face_indices.reshape(-1, 3)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    boundary = int(np.count_nonzero(counts == 1))
    if boundary == 0:
        return None
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.points, face_matrix=faces))
    ms.set_selection_none()
    ms.meshing_close_holes(maxholesize=boundary + 1, selfintersection=False,
                           newfaceselected=True)
    m = ms.current_mesh()
    if m.vertex_number() != mesh.points.shape[0]:
        raise InputError("sealing the scan moved its vertices", mesh.source)
    new = np.asarray(m.face_matrix(), dtype=np.int64)[np.asarray(m.face_selection_array(), bool)]
    if new.shape[0] == 0:
        raise InputError(f"could not seal the scan's {boundary} boundary edges", mesh.source)
    used, tris = np.unique(new, return_inverse=True)
    return validate_mesh(replace(mesh, points=mesh.points[used],
                                 face_counts=np.full(new.shape[0], 3, np.int32),
                                 face_indices=tris.reshape(-1).astype(np.int32), st=None))


PREPARE_TIMEOUT_S = 600.0


class ScanPreparation:
    """:func:`prepare_scan` and :func:`seal_scan` of a triangle mesh in a child process
    started at once (``_prepare_child``), so that the caller works meanwhile: the demo
    ingests and fits while the face scan is cleaned and decimated (4 s), and a pymeshlab
    crash there is an error here. :meth:`result` waits; :meth:`close` (or leaving a
    ``with`` block) stops a child no one waits for and removes its files."""

    def __init__(self, mesh: MeshData, target_faces: int = 60000) -> None:
        if np.any(mesh.face_counts != 3):
            raise InputError("prepare_scan needs a triangle mesh", mesh.source)
        self._mesh = mesh
        self._tmp = tempfile.TemporaryDirectory(prefix="skinpipe-prepare-")
        folder = Path(self._tmp.name)
        self._out = folder / "prepared.npz"
        np.savez(folder / "scan.npz", points=mesh.points,
                 faces=mesh.face_indices.reshape(-1, 3), meters_per_unit=mesh.meters_per_unit)
        self._proc = subprocess.Popen(
            python_command("-m", "skinpipe.usd._prepare_child", str(folder / "scan.npz"),
                           str(self._out), str(int(target_faces))),
            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)

    def result(self, timeout_s: float = PREPARE_TIMEOUT_S) -> tuple[MeshData, MeshData | None]:
        """The prepared mesh and its seal (None for a closed mesh), as
        :func:`prepare_scan` and :func:`seal_scan` make them."""
        try:
            _, err = self._proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.close()
            raise InputError(f"preparing the scan took over {timeout_s:.0f} s",
                             self._mesh.source) from None
        if self._proc.returncode != 0 or not self._out.is_file():
            why = child_failure("pymeshlab", self._proc.returncode, err,
                                "skinpipe-prepare-error:")
            raise InputError(f"cannot prepare the scan: {why}", self._mesh.source)
        with np.load(self._out) as data:
            prepared = self._mesh_of(data["points"], data["faces"])
            seal = self._mesh_of(data["seal_points"], data["seal_faces"]) \
                if "seal_points" in data.files else None
        return prepared, seal

    def _mesh_of(self, points: NDArray[Any], faces: NDArray[Any]) -> MeshData:
        return validate_mesh(replace(self._mesh, points=np.asarray(points, np.float64),
                                     face_counts=np.full(faces.shape[0], 3, np.int32),
                                     face_indices=np.asarray(faces, np.int32).reshape(-1),
                                     st=None))

    def close(self) -> None:
        if self._proc.poll() is None:
            self._proc.kill()
            self._proc.communicate()
        self._tmp.cleanup()

    def __enter__(self) -> ScanPreparation:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def pymeshlab_face_scan() -> Path:
    """The real face range scan shipped in pymeshlab's wheel (mm units, holes, noise)."""
    path = pymeshlab_folder() / "tests" / "sample_meshes" / "rangemaps" / "face000.ply"
    if not path.is_file():
        raise InputError("pymeshlab's sample face scan is not installed", path)
    return path
