"""UV unwrapping with xatlas, guarded: validated input, bounded time.

xatlas hangs on a single non-finite vertex or on coordinates near 1e20, returns NaN
UVs for degenerate meshes without raising, and spends minutes building charts on raw
scans. The mesh is validated first, xatlas runs in a child process that is killed
after ``timeout_s``, and the UVs that come back are checked.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue as queue_mod
import signal
import tempfile
import time
from dataclasses import dataclass
from queue import Empty
from typing import Any

import numpy as np
import xatlas
from numpy.typing import NDArray

from ..errors import InputError, SkinpipeError
from ..usd.mesh import MeshData, validate_mesh


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


def _xatlas_child(npz: str, chart_area: float, resolution: int, padding: int,
                  queue: Any) -> None:
    # Ctrl-C reaches the whole process group: the parent stops this child, which must
    # not print a traceback of its own
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _run_xatlas(npz, chart_area, resolution, padding, queue)


def _run_xatlas(npz: str, chart_area: float, resolution: int, padding: int, queue: Any) -> None:
    with np.load(npz) as data:
        points, tris = data["points"], data["tris"]
    atlas = xatlas.Atlas()
    atlas.add_mesh(points, tris)
    chart = xatlas.ChartOptions()
    if chart_area > 0:
        chart.max_chart_area = chart_area
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.padding = padding
    atlas.generate(chart, pack)
    vmapping, indices, uvs = atlas[0]
    queue.put((np.asarray(vmapping), np.asarray(indices), np.asarray(uvs),
               int(atlas.chart_count), float(np.mean(atlas.utilization))))


def _xatlas_in_child(npz: str, chart_area: float, resolution: int, padding: int,
                     timeout_s: float, start: float) -> Any:
    """Run :func:`_run_xatlas` in a spawned child: a crash there is an error here."""
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=_xatlas_child, args=(npz, chart_area, resolution, padding, queue),
                       daemon=True)
    result = None
    ok = False
    try:
        proc.start()
        while result is None:
            try:
                result = queue.get(timeout=0.2)
            except Empty:
                if not proc.is_alive() and queue.empty():
                    raise SkinpipeError(f"xatlas crashed (exit code {proc.exitcode})") from None
                if time.perf_counter() - start > timeout_s:
                    raise SkinpipeError(f"xatlas did not finish in {timeout_s:.0f} s; decimate "
                                        "the mesh or raise charts_per_mesh") from None
        ok = True
    finally:
        if proc.pid is not None:
            if not ok:  # interrupted or failed: nothing to wait for
                proc.kill()
            proc.join(timeout=5)
            if proc.is_alive():
                proc.kill()
    return result


def unwrap(mesh: MeshData, resolution: int = 2048, padding: int = 4,
           charts_per_mesh: int = 100, timeout_s: float = 300.0) -> UVLayout:
    """Unwrap with xatlas in a child process. ``charts_per_mesh`` caps each chart's area
    at total area / charts_per_mesh, which keeps noisy scans from taking minutes
    (measured on the face scan decimated to 50k faces: 32 s uncapped, 2.4 s at 100)."""
    validate_mesh(mesh)
    tris = triangulate(mesh)
    p = mesh.points[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    if not area.sum() > 0:
        raise InputError("the mesh has no area (every face is degenerate)", mesh.source)
    start = time.perf_counter()
    chart_area = float(area.sum() / charts_per_mesh) if charts_per_mesh else 0.0
    # The mesh goes through a file: spawn pickles arguments into a pipe that blocks the
    # parent for good if the child dies before reading them.
    tmp = tempfile.NamedTemporaryFile(suffix=".npz", delete=False)
    tmp.close()
    np.savez(tmp.name, points=mesh.points.astype(np.float32), tris=tris.astype(np.uint32))
    try:
        if mp.current_process().daemon:
            # a daemonic process (a Dask worker by default) may not have children: run
            # here; a crash then takes down the worker, which its nanny restarts
            local: queue_mod.Queue[Any] = queue_mod.Queue()
            _run_xatlas(tmp.name, chart_area, resolution, padding, local)
            result = local.get_nowait()
        else:
            result = _xatlas_in_child(tmp.name, chart_area, resolution, padding, timeout_s,
                                      start)
    finally:
        os.unlink(tmp.name)
    vmapping, indices, uvs, charts, util = result
    seconds = time.perf_counter() - start
    uvs = np.asarray(uvs, dtype=np.float64)
    if not np.all(np.isfinite(uvs)):
        raise SkinpipeError("xatlas returned non-finite UVs (degenerate geometry?)")
    # xatlas re-indexes vertices (seams split them); UVs stay tied to output vertices,
    # and vmapping says which input vertex each came from. Faces keep their order.
    out_tris = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    if out_tris.shape[0] != tris.shape[0] or not np.array_equal(
            np.asarray(vmapping)[out_tris], tris):
        raise SkinpipeError("xatlas changed the triangle list; cannot map UVs back")
    return UVLayout(uvs, out_tris.reshape(-1).astype(np.int32), charts, util, seconds)
