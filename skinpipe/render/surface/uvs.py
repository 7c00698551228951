"""A skin mesh's UVs: whether the authored ones can carry texture-space diffusion
(finite, in [0, 1], not overlapping, few degenerate faces), an xatlas unwrap where they
cannot (regions charted side by side), written back into the mesh's layer."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from pxr import Sdf, Usd, UsdGeom, Vt

from ...errors import InputError
from ...usd.io import export_layer_atomic, open_stage_guarded
from ..scene import SceneData, SceneDelegate, SceneMesh
from .unwrap import diffusion_chart_area, triangulate, unwrap


def uv_triangles(mesh: SceneMesh) -> NDArray[np.int32] | None:
    """UV indices per triangle corner (the same fan triangulation as the mesh)."""
    if mesh.uv is None:
        return None
    if mesh.uv_indices is None:
        return triangulate(mesh.mesh)
    # triangulate the face-vertex positions exactly as the vertex indices are
    fv = replace(mesh.mesh, face_indices=np.arange(mesh.mesh.face_indices.size, dtype=np.int32))
    return mesh.uv_indices[triangulate(fv)]


def usable_uvs(mesh: SceneMesh) -> str | None:
    """None if the mesh's ``st`` can carry texture-space diffusion, else why not."""
    if mesh.uv is None:
        return "no st primvar"
    uv = mesh.uv
    if not np.all(np.isfinite(uv)):
        return "non-finite st values"
    if uv.min() < -1e-6 or uv.max() > 1 + 1e-6:
        return "st outside [0, 1]"
    if mesh.uv_indices is not None and (mesh.uv_indices.size != mesh.mesh.face_indices.size or
                                        mesh.uv_indices.min() < 0 or
                                        mesh.uv_indices.max() >= uv.shape[0]):
        return "st indices do not match the faces"
    if mesh.uv_indices is None and uv.shape[0] != mesh.mesh.points.shape[0]:
        return "per-vertex st has the wrong length"
    tq = uv[uv_triangles(mesh)]  # type: ignore[index]
    e1, e2 = tq[:, 1] - tq[:, 0], tq[:, 2] - tq[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    if np.count_nonzero(area > 0) < 0.95 * area.size:
        return "more than 5% of the faces have zero UV area"
    if area.sum() > 1.05:
        return "UV triangles overlap (total UV area > 1)"
    return None


def write_uvs_back(stage: Any, mesh: SceneMesh, uv: NDArray[Any], uv_indices: NDArray[Any]
                   ) -> str | None:
    """Author faceVarying indexed ``st`` in the layer that holds the mesh's points and save
    it atomically; returns the layer path, or None when it cannot be done safely."""
    if mesh.points_layer is None:
        return None
    layer = Sdf.Layer.FindOrOpen(mesh.points_layer)
    if layer is None or not layer.realPath or layer.anonymous:
        return None
    layer_stage = Usd.Stage.Open(layer)
    prim = layer_stage.GetPrimAtPath(mesh.points_prim or mesh.path)
    if not prim:
        return None
    pv = UsdGeom.PrimvarsAPI(prim).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
    pv.Set(Vt.Vec2fArray.FromNumpy(np.asarray(uv, np.float32)))
    pv.SetIndices(Vt.IntArray.FromNumpy(np.asarray(uv_indices, np.int32)))
    export_layer_atomic(layer, layer.realPath)
    return str(layer.realPath)


def region_pieces(mesh: SceneMesh) -> NDArray[np.int32] | None:
    """Each triangle's region (the largest of its corners' summed region weights), for
    xatlas to chart a skin mesh's regions side by side (:func:`~.unwrap.unwrap`); None
    for a mesh with fewer than two regions."""
    if mesh.region_weights is None or len(mesh.region_names) < 2:
        return None
    corners = mesh.region_weights[triangulate(mesh.mesh)]
    return np.argmax(corners.sum(axis=1), axis=1).astype(np.int32)


def widest_variance_mm2(mesh: SceneMesh) -> float:
    """The widest term any of the mesh's profiles gives light (weight over 1e-3 in a
    channel), 0 for a mesh without profiles."""
    return max((float(np.max(f.variances_mm2[np.max(f.weights, axis=1) > 1e-3],
                              initial=0.0)) for f in mesh.fits), default=0.0)


def unwrap_and_write_back(stage: Any, mesh: SceneMesh, reason: str, write: bool,
                          progress: Callable[[str], None] | None = None
                          ) -> tuple[NDArray[np.float64], NDArray[np.int32], dict[str, Any]]:
    """xatlas UVs for a mesh whose ``st`` is unusable (``reason``), rounded to float32 as
    USD stores them, and written back into the mesh's layer when ``write`` (triangle
    meshes only: a polygon split across charts has no faceVarying form)."""
    if progress:
        progress(f"unwrap {mesh.path} with xatlas ({reason})")
    layout = unwrap(mesh.mesh, pieces=region_pieces(mesh),
                    min_chart_area=diffusion_chart_area(widest_variance_mm2(mesh),
                                                        mesh.mesh.meters_per_unit))
    uv = layout.uv.astype(np.float32).astype(np.float64)
    measures: dict[str, Any] = {"charts": layout.charts, "utilization": layout.utilization,
                                "seconds": layout.seconds, "reason": reason}
    if write and np.all(mesh.mesh.face_counts == 3):
        measures["written_to"] = write_uvs_back(stage, mesh, uv, layout.uv_indices)
    return uv, layout.uv_indices.reshape(-1, 3), measures


class SkinUVs(NamedTuple):
    stage: Any
    scene: SceneData
    mesh: SceneMesh
    uv: NDArray[np.float64]
    uv_triangles: NDArray[np.int32]
    note: str  # "kept" or "unwrapped (why)"


def ensure_skin_uvs(asset: Path, progress: Callable[[str], None] | None = None) -> SkinUVs:
    """The first skin mesh of ``asset`` with usable UVs: xatlas and written back into the
    asset's layer when it has none."""
    stage = open_stage_guarded(asset)
    delegate = SceneDelegate(stage)
    try:
        scene = delegate.sync()
    finally:
        delegate.close()
    if not scene.skin:
        raise InputError("no skin mesh (SkinProfileRegionsAPI)", asset)
    mesh = scene.skin[0]
    why = usable_uvs(mesh)
    if why is None:
        uv, uv_tris = mesh.uv, uv_triangles(mesh)
        assert uv is not None and uv_tris is not None
        return SkinUVs(stage, scene, mesh, uv, uv_tris, "kept")
    uv, uv_tris, measures = unwrap_and_write_back(stage, mesh, why, True, progress)
    if measures.get("written_to") is None:
        raise InputError(f"cannot write UVs into the layer holding {mesh.path}", asset)
    return SkinUVs(stage, scene, mesh, uv, uv_tris, f"unwrapped ({why})")
