"""UV unwrapping with xatlas, guarded: validated input, bounded time.

xatlas hangs on a single non-finite vertex or on coordinates near 1e20, returns NaN
UVs for degenerate meshes without raising, and spends minutes building charts on raw
scans. The mesh is validated first, xatlas runs in a child process that is killed
after ``timeout_s``, and the UVs that come back are checked.
"""

from __future__ import annotations

import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...children import child_failure, python_command
from ...errors import InputError, SkinpipeError
from ...usd.mesh import MeshData, validate_mesh


@dataclass(frozen=True)
class UVLayout:
    """Face-varying texture coordinates: ``uv`` (U, 2) in [0, 1] and, per face vertex of
    the mesh's triangulation, an index into ``uv``; plus xatlas' facts."""

    uv: NDArray[np.float64]
    uv_indices: NDArray[np.int32]
    charts: int
    utilization: float
    seconds: float


def triangulate(mesh: MeshData) -> NDArray[np.int32]:
    """Fan-triangulate the mesh's faces: (T, 3) vertex indices, and keep face order."""
    counts = mesh.face_counts
    if np.all(counts == 3):
        return mesh.face_indices.reshape(-1, 3)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = []
    for s, c in zip(starts, counts, strict=True):
        for k in range(1, c - 1):
            tris.append((mesh.face_indices[s], mesh.face_indices[s + k],
                         mesh.face_indices[s + k + 1]))
    return np.asarray(tris, dtype=np.int32)


_CHILD = Path(__file__).with_name("_xatlas_child.py")


def _xatlas_in_child(points: NDArray[Any], tris: NDArray[Any], pieces: NDArray[Any],
                     chart_area: float, resolution: int, padding: int, timeout_s: float
                     ) -> dict[str, Any]:
    """xatlas in a child process (``_xatlas_child.py``): a crash there, or a run past
    ``timeout_s``, is an error here. A child process also from a daemonic one (a Dask
    worker), which may not fork children of its own through multiprocessing."""
    with tempfile.TemporaryDirectory(prefix="skinpipe-xatlas-") as tmp:
        mesh, out = Path(tmp) / "mesh.npz", Path(tmp) / "uv.npz"
        np.savez(mesh, points=points.astype(np.float32), tris=tris.astype(np.uint32),
                 pieces=pieces.astype(np.int32))
        try:
            proc = subprocess.run(
                python_command(str(_CHILD), str(mesh), str(out), repr(chart_area),
                               str(resolution), str(padding)),
                capture_output=True, text=True, timeout=timeout_s)
        except subprocess.TimeoutExpired:
            raise SkinpipeError(f"xatlas did not finish in {timeout_s:.0f} s; decimate the "
                                "mesh or raise charts_per_mesh") from None
        if proc.returncode != 0 or not out.is_file():
            raise SkinpipeError(child_failure("xatlas", proc.returncode, proc.stderr))
        with np.load(out) as npz:
            return {key: npz[key] for key in npz.files}


CHART_SIGMAS = 8.0
"""A chart's side, in standard deviations of the profile's widest term, below which
xatlas's area cap may not cut (:func:`diffusion_chart_area`). An area is not a width:
xatlas cuts a tube of radius 5 mm capped at (4 sigma)^2 into rings 1.4 mm long, as
narrow as the first cap's charts; at (8 sigma)^2 into six charts."""


def diffusion_chart_area(widest_variance_mm2: float, meters_per_unit: float) -> float:
    """The least chart area (scene units squared) for a profile whose widest term has
    ``widest_variance_mm2``: (CHART_SIGMAS sigma)^2. Light crosses a seam through the
    chart tiles' margins, which each level of the blur pyramid fills from the
    neighbouring charts' fully covered texels; a chart much narrower than the widest
    term has none at that term's level, and its light steps at every seam (a sphere of
    radius 10 mm cut into 200 charts of 3.5 mm under skin1's 4.7 mm term: whole charts
    brighter or darker by 7-15% beyond the terminator)."""
    side_mm = CHART_SIGMAS * float(np.sqrt(max(widest_variance_mm2, 0.0)))
    return (side_mm / (meters_per_unit * 1000.0)) ** 2


def unwrap(mesh: MeshData, resolution: int = 2048, padding: int = 4,
           charts_per_mesh: int = 100, timeout_s: float = 300.0,
           pieces: NDArray[Any] | None = None, min_chart_area: float = 0.0) -> UVLayout:
    """Unwrap with xatlas in a child process. ``charts_per_mesh`` caps each chart's area
    at total area / charts_per_mesh, which keeps noisy scans from taking minutes
    (measured on the face scan decimated to 50k faces: 32 s uncapped, 2.4 s at 100),
    but never below ``min_chart_area`` (scene units squared; see
    :func:`diffusion_chart_area`).

    ``pieces`` (a small integer per triangle of :func:`triangulate`, e.g. a face's
    regions) splits the mesh into pieces that xatlas charts side by side on its threads;
    no chart crosses from one piece to another. The sample face by its six regions:
    xatlas a third faster on two cores."""
    validate_mesh(mesh)
    tris = triangulate(mesh)
    if pieces is None:
        pieces = np.zeros(tris.shape[0], np.int32)
    pieces = np.asarray(pieces)
    if pieces.shape != (tris.shape[0],) or not np.issubdtype(pieces.dtype, np.integer):
        raise InputError(f"pieces: one integer per triangle ({tris.shape[0]}), got "
                         f"{pieces.dtype} {pieces.shape}", mesh.source)
    p = mesh.points[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if not area.sum() > 0:
        raise InputError("the mesh has no area (every face is degenerate)", mesh.source)
    start = time.perf_counter()
    chart_area = max(float(area.sum() / charts_per_mesh), float(min_chart_area)) \
        if charts_per_mesh else 0.0
    result = _xatlas_in_child(mesh.points, tris, pieces, chart_area, resolution, padding,
                              timeout_s)
    seconds = time.perf_counter() - start
    uvs = np.asarray(result["uvs"], dtype=np.float64)
    if not np.all(np.isfinite(uvs)):
        raise SkinpipeError("xatlas returned non-finite UVs (degenerate geometry?)")
    # xatlas re-indexes vertices (seams split them); UVs stay tied to output vertices,
    # and vmapping says which input vertex each came from. Faces keep their order.
    out_tris = np.asarray(result["indices"], dtype=np.int64).reshape(-1, 3)
    if out_tris.shape[0] != tris.shape[0] or not np.array_equal(
            np.asarray(result["vmapping"])[out_tris], tris):
        raise SkinpipeError("xatlas changed the triangle list; cannot map UVs back")
    return UVLayout(uvs, out_tris.reshape(-1).astype(np.int32), int(result["charts"]),
                    float(result["utilization"]), seconds)
