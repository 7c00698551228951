"""Render stage: texture-space diffusion of a face from a USD asset (paper, sections 3-4).

Tasks, each cached on the content of its inputs (so a turntable computes the
texture-space work once and re-runs only the camera's shading):

    uvs -> texture maps -> irradiance -> albedo map -> diffusion -> shade -> output

Units: texture-space radii and variances in mm (the stretch map turns scene units into
mm with the stage's metersPerUnit); colours linear in the stage's working space
(ACEScg, OCIO ``lin_ap1_scene``) until the display PNG.
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor, wait
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import PyOpenColorIO as OCIO
from numpy.typing import NDArray
from pxr import Sdf, Tf, Usd, UsdGeom, Vt

from ..errors import InputError, SkinpipeError
from ..fileio import atomic_write_json
from ..imageio import (
    check_colorspace,
    convert_colorspace,
    ocio_config,
    read_image,
    write_exr,
    write_ldr,
)
from ..profile.models import fit_error_eq2c, sum_of_gaussians
from ..profile.types import FitResult
from ..usd.io import export_layer_atomic, open_stage_guarded
from .bands import BAND_ITEMS, BAND_THREADS, beside, host_threads, in_bands
from .blur_switch import TUNE_STREAM, direct_limits, tuning_kernels
from .chart_tiles import margin_kernels, seam_read_kernel
from .diffusion import (
    DiffusionLayout,
    chart_layout,
    diffuse_gather,
    diffuse_prepared,
    pyramid_kernels,
    release_freed_heap,
)
from .direct_blur import texel_kernels
from .huge_pages import apply_to_numpy, huge_pages_choice
from .kept import kept, source_of
from .lighting import (
    IrradianceResult,
    filter_interleaved,
    interleave_period,
    irradiance_kernels,
    irradiance_texture,
    light_direction,
    refine_penumbrae,
    sobol_points,
    specular_albedo,
    torrance_sparrow,
    visibility_plane,
    visibility_planes,
)
from .opencl import (
    LEDGER,
    KernelLedger,
    device_choice,
    set_device,
    start_prewarm,
    streams,
)
from .options import AOVS, DATA_AOVS, RenderOptions
from .push_pull import dilate_charts, prepare_dilation, push_pull, push_pull_kernels
from .raytrace import RayScene, offset_ray_origin
from .recursive_blur import pass_kernels
from .resample import (
    EXACT_POWERS,
    put_rows,
    resample_bilinear,
    resampled_texels,
    take_rows,
    times_resampled_power,
)
from .scene import Camera, SceneData, SceneDelegate, SceneMesh, content_hash
from .texture_maps import (
    TextureMaps,
    rasterize,
    texel_rows,
    texels_in_blocks,
    texture_kernels,
    vertex_normals,
)
from .tile_store import TileStore
from .unwrap import triangulate, unwrap

EDGE_SAMPLES = ((0.125, -0.375), (0.375, 0.125), (-0.125, 0.375), (-0.375, -0.125))
"""Sub-pixel offsets (pixels) of a silhouette pixel's camera rays: the 4-rook rotated
grid, one sample in every row and column of a 4 x 4 subdivision."""
HALF_MAX = 65504.0
"""The largest finite half float."""
MERGE_RELATIVE = 1e-3
"""Variances closer than this (relative) share one blur."""


# ------------------------------------------------------------------------ profiles


@dataclass(frozen=True)
class DiffusionTerms:
    """Variances (K,) mm^2 shared by all regions and each region's weights (R, K, 3),
    with the eq. 2c error of re-expressing each region's fit on them."""

    variances_mm2: NDArray[np.float64]
    weights: NDArray[np.float64]
    error: dict[str, float]
    notes: list[str]


def _normalised(fit: FitResult) -> NDArray[np.float64]:
    s = fit.weights.sum(axis=0, keepdims=True)
    return fit.weights / np.where(s > 0, s, 1.0)


def diffusion_terms(fits: list[FitResult] | tuple[FitResult, ...], grid: int = 0,
                    single: str | None = None, floor_mm2: float = 0.0) -> DiffusionTerms:
    """The blur schedule for a set of region fits.

    ``grid`` = 0 keeps every fit's own variances (equal ones merged). ``grid`` = N
    re-expresses each region and channel on the smallest variance plus N - 1 log-spaced
    ones from ``floor_mm2`` (narrower blurs are sub-texel and cost nothing) to the
    largest, by
    non-negative least squares on the r-weighted profile (the fit's eq. 2c objective),
    then renormalises the weights to sum to 1. ``single`` = 'mean' or a region name
    gives every region the same profile (the paper's comparison with one profile).
    """
    from scipy.optimize import nnls  # lazy: 0.50 s to import

    fits = list(fits)
    notes: list[str] = []
    if single is not None:
        names = [f.name for f in fits]
        if single != "mean" and single not in names:
            raise InputError(f"single profile {single!r}: not one of {names} or 'mean'")
    all_v = np.concatenate([f.variances_mm2 for f in fits])
    if grid > 0:
        lo, hi = float(all_v.min()), float(all_v.max())
        start = min(max(lo, floor_mm2), hi)
        variances = np.unique(np.concatenate([[lo], np.geomspace(start, hi, grid - 1)])) \
            if grid > 1 and hi > lo * 1.0001 else np.array([lo])
    else:
        variances = np.sort(all_v)
        keep = np.concatenate([[True], np.diff(variances) > MERGE_RELATIVE * variances[1:]])
        merged = int((~keep).sum())
        if merged:
            notes.append(f"{merged} equal variance(s) merged into one blur")
        variances = variances[keep]
    weights = np.zeros((len(fits), variances.size, 3))
    error: dict[str, float] = {}
    for r, fit in enumerate(fits):
        w = _normalised(fit)
        if grid > 0:
            radius = np.linspace(0.0, 4.0 * math.sqrt(variances.max()), 400)[1:]
            basis = np.stack([sum_of_gaussians([v], [[1, 1, 1]], radius)[:, 0]
                              for v in variances], axis=1)
            target = sum_of_gaussians(fit.variances_mm2, w, radius)
            sw = np.sqrt(radius)[:, None]
            for c in range(3):
                a, _ = nnls(basis * sw, target[:, c] * sw[:, 0])
                weights[r, :, c] = a / max(a.sum(), 1e-30)
            approx = sum_of_gaussians(variances, weights[r], radius)
            error[fit.name] = float(fit_error_eq2c(radius, approx, target).max())
        else:
            for v, row in zip(fit.variances_mm2, w, strict=True):
                k = int(np.argmin(np.abs(variances - v)))
                weights[r, k] += row
            error[fit.name] = 0.0
    if single is not None:
        shared = weights.mean(axis=0) if single == "mean" else \
            weights[[f.name for f in fits].index(single)]
        weights[:] = shared
        notes.append(f"one profile ({single}) for every region")
    return DiffusionTerms(variances, weights, error, notes)


def kept_diffusion_terms(fits: list[FitResult] | tuple[FitResult, ...], grid: int = 0,
                         single: str | None = None, floor_mm2: float = 0.0
                         ) -> DiffusionTerms:
    """:func:`diffusion_terms`, kept in skinpipe's cache folder (:mod:`.kept`) by scipy's
    version, the source of the functions that make them and every input (the fits'
    names, variances and weights, ``grid``, ``single``, ``floor_mm2``): the same terms
    bit for bit. Importing scipy.optimize for its NNLS took 0.44 s of a render's main
    thread before its rays (0.5 s of CPU, the other core mostly idle); a render of the
    same fits at the same texel size reads them back instead."""
    import scipy

    fits = list(fits)
    # the code that makes them is in the key too, with scipy's version: terms made by an
    # edited function are not read back
    code = source_of(diffusion_terms, _normalised, sum_of_gaussians, fit_error_eq2c)
    key = content_hash(scipy.__version__, code, MERGE_RELATIVE, grid, single,
                       float(floor_mm2), len(fits),
                       *(part for f in fits for part in
                         (f.name, np.asarray(f.variances_mm2, np.float64),
                          np.asarray(f.weights, np.float64))))

    def read(doc: dict[str, Any]) -> DiffusionTerms:
        variances = np.asarray(doc["variances_mm2"], np.float64)
        weights = np.asarray(doc["weights"], np.float64)
        error = {str(k): float(v) for k, v in doc["error"].items()}
        if variances.ndim != 1 or weights.shape != (len(fits), variances.size, 3) \
                or set(error) != {f.name for f in fits} \
                or not np.all(np.isfinite(weights)) or not np.all(variances > 0):
            raise ValueError("kept terms do not fit the fits")
        return DiffusionTerms(variances, weights, error, [str(n) for n in doc["notes"]])

    def make() -> tuple[DiffusionTerms, dict[str, Any]]:
        terms = diffusion_terms(fits, grid, single, floor_mm2)
        return terms, {"variances_mm2": terms.variances_mm2.tolist(),
                       "weights": terms.weights.tolist(), "error": terms.error,
                       "notes": terms.notes}

    return kept("diffusion-terms", "terms", key, read, make)


# ------------------------------------------------------------------------ helpers


def interleave_classes(shape: tuple[int, int], period: int = 2) -> NDArray[np.uint8]:
    """Each texel's interleaving class for the ``period`` p, p (y mod p) + (x mod p),
    flat in row order: one byte a texel, from rows' and columns' remainders (the texels'
    flat indices' divisions and remainders in int64 took 0.21-0.23 s at texture 4096,
    this 0.02 s)."""
    h, w = shape
    rows = (np.arange(h) % period * period).astype(np.uint8)
    columns = (np.arange(w) % period).astype(np.uint8)
    return (rows[:, None] + columns[None, :]).ravel()


def texels_per_pixel(points: NDArray[Any], tris: NDArray[Any], uv: NDArray[Any],
                     uv_tris: NDArray[Any], texture_size: int, camera: Camera,
                     width: int) -> float:
    """How many texels of a ``texture_size`` texture lie across one pixel of a ``width``
    pixels wide image at the skin: the pixel's side over the texel's, both in scene
    units. The texel's mean side is sqrt(A / (A_uv S^2)) (the mesh's area over its UV
    area); the pixel's is its footprint at the triangles' median depth along the
    camera's axis (perspective: depth x aperture / focal length / width; orthographic:
    aperture / width). 0 where either cannot be told (no area, behind the camera)."""
    corners = np.asarray(points, np.float64)[tris]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0],
                                         corners[:, 2] - corners[:, 0]), axis=1).sum()
    t = np.asarray(uv, np.float64)[uv_tris]
    e1, e2 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    uv_area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum()
    if not (area > 0 and uv_area > 0 and width > 0):
        return 0.0
    texel = math.sqrt(area / uv_area) / texture_size
    if camera.projection == "orthographic":
        pixel = camera.horizontal_aperture / width
    else:
        depth = float(np.median((corners.mean(axis=1) - camera.position)
                                @ -camera.rotation[:, 2]))
        pixel = depth * camera.horizontal_aperture / camera.focal_length / width
    return pixel / texel if pixel > 0 and math.isfinite(pixel / texel) else 0.0


def interleaved_visibility(res: IrradianceResult, maps: TextureMaps,
                           texel: NDArray[np.intp] | None = None, period: int = 2,
                           normal: NDArray[np.float32] | None = None
                           ) -> dict[str, NDArray[np.float32]]:
    """Each light's per-texel visibility from interleaved shadow rays of ``period``,
    reconstructed in texture space (``filter_interleaved``) and returned per covered
    texel (``texel``: the points' flat indices, in their order; by default row order).
    ``normal``: the maps' normal map where they let it go (:func:`normal_map`)."""
    covered = maps.triangle >= 0
    if texel is None:
        texel = np.flatnonzero(covered)
    paths = [p for p in res.visibility if p in res.interleaved]
    if not paths:  # no light was interleaved: nothing to reconstruct
        return dict(res.visibility)
    vis = visibility_planes(len(paths), covered.shape)
    for i, p in enumerate(paths):
        visibility_plane(res.visibility[p], res.carries_light(p), texel, vis[i])
    filtered = filter_interleaved(vis, None, maps.surface[1] if normal is None else normal,
                                  at=texel, period=period)
    return {**res.visibility, **dict(zip(paths, filtered, strict=True))}


def normal_map(normals: NDArray[np.float32], texel: NDArray[np.intp],
               shape: tuple[int, int]) -> NDArray[np.float32]:
    """The (H, W, 3) normal map of ``shape`` from its covered texels' rows (``normals``
    at flat indices ``texel``), zero elsewhere as :func:`~.texture_maps.rasterize` leaves
    it: the same map, made again from the rows the irradiance keeps."""
    out = np.zeros((*shape, 3), np.float32)
    put_rows(out.reshape(-1, 3), texel, normals)
    return out


LOOKUP_BAND_POINTS = 1 << 17
"""Points a band of :func:`bilinear` looks up on one core (1.5 MB of RGB float32 out)."""


def bilinear(texture: NDArray[Any], uv: NDArray[Any]) -> NDArray[np.float32]:
    """Bilinear lookup of a (S, S, C) texture map (row j holds v = (j + 0.5) / S) at uv."""
    size_v, size_u = texture.shape[:2]
    flat = np.asarray(texture, np.float32).reshape(size_v * size_u, -1)
    # in bands of points on the host's cores: each point's four reads miss the cache
    # of a large map (the demo face's radiance at texture 4096, 0.6 M hits: 0.2 s on
    # one core)
    def band(s: slice) -> NDArray[np.float32]:
        return bilinear_of(lambda i: take_rows(flat, i), (size_v, size_u), uv[s])

    if len(uv) <= LOOKUP_BAND_POINTS:
        return band(slice(None))
    return np.concatenate(in_bands(band, len(uv), LOOKUP_BAND_POINTS))


def bilinear_of(texels: Callable[[NDArray[np.int64]], NDArray[np.float32]],
                shape: tuple[int, int], uv: NDArray[Any]) -> NDArray[np.float32]:
    """:func:`bilinear` of a texture of ``shape`` (rows, columns) that ``texels`` gives
    at flat texel indices (N,) as (N, C), rather than a map held whole."""
    size_v, size_u = shape
    x = np.clip(np.asarray(uv[:, 0], np.float32) * size_u - 0.5, 0, size_u - 1)
    y = np.clip(np.asarray(uv[:, 1], np.float32) * size_v - 0.5, 0, size_v - 1)
    x0 = np.minimum(x.astype(np.int64), size_u - 2 if size_u > 1 else 0)
    y0 = np.minimum(y.astype(np.int64), size_v - 2 if size_v > 1 else 0)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    dx, dy = int(size_u > 1), (size_u if size_v > 1 else 0)
    i = y0 * size_u + x0
    top = texels(i) * (1 - fx) + texels(i + dx) * fx
    bottom = texels(i + dy) * (1 - fx) + texels(i + dy + dx) * fx
    return top * (1 - fy) + bottom * fy


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


def unwrap_and_write_back(stage: Any, mesh: SceneMesh, reason: str, write: bool,
                          progress: Callable[[str], None] | None = None
                          ) -> tuple[NDArray[np.float64], NDArray[np.int32], dict[str, Any]]:
    """xatlas UVs for a mesh whose ``st`` is unusable (``reason``), rounded to float32 as
    USD stores them, and written back into the mesh's layer when ``write`` (triangle
    meshes only: a polygon split across charts has no faceVarying form)."""
    if progress:
        progress(f"unwrap {mesh.path} with xatlas ({reason})")
    layout = unwrap(mesh.mesh, pieces=region_pieces(mesh))
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


def albedo_image(mesh: SceneMesh, working: str) -> tuple[NDArray[np.float32], str]:
    """The albedo's own image, linear in the working space, in texture row order (the
    bottom row first; (1, 1, 3) for a constant), and what it came from. Its texture-space
    map is the image resampled (:func:`albedo_texture`)."""
    albedo = mesh.albedo
    if albedo.texture is None:
        return np.asarray(albedo.constant, np.float32).reshape(1, 1, 3), \
            "constant diffuseColor"
    img = read_image(albedo.texture)
    cs = albedo.colorspace or (working if img.is_float else "srgb_tx")
    px = img.pixels if cs == working else convert_colorspace(img.pixels, cs, working)
    # texture-space row j holds v = (j + 0.5) / size; image row 0 is the top (v = 1)
    return np.ascontiguousarray(px[::-1, :, :3], dtype=np.float32), f"{albedo.texture} ({cs})"


def albedo_texture(image: NDArray[np.float32], size: int) -> NDArray[np.float32]:
    """The albedo map (S, S, 3) of :func:`albedo_image`'s ``image``: resampled to the
    texel centres, bilinear, and no less than 0."""
    out = resample_bilinear(image, size)
    return np.clip(out, 0.0, None, out=out)


def albedo_texels(image: NDArray[np.float32], size: int
                  ) -> Callable[[NDArray[np.int64]], NDArray[np.float32]]:
    """The texels of ``albedo_texture(image, size)`` at flat indices, the same floats,
    for :func:`bilinear_of`: lookups without the map."""
    def texels(index: NDArray[np.int64]) -> NDArray[np.float32]:
        out = resampled_texels(image, size, index)
        return np.clip(out, 0.0, None, out=out)
    return texels


# ------------------------------------------------------------------------ renderer


def ray_owners(camera_rays: RayScene, prim: NDArray[Any]) -> NDArray[Any]:
    """Per ray the (mesh, triangle) of the scene its hit ``prim`` in ``camera_rays``
    belongs to, (-1, -1) for a miss."""
    return np.where(prim[:, None] >= 0, camera_rays.owner[np.maximum(prim, 0)], -1)


def mesh_hits(owner: NDArray[Any], hits: tuple[NDArray[Any], ...], mesh: int
              ) -> tuple[NDArray[np.intp], NDArray[Any], NDArray[np.float64]]:
    """The rays whose first hit is on scene mesh ``mesh`` (indices), their triangles
    and barycentrics (N, 3, 1), from :func:`ray_owners` and the hits (prim, u, v, t)."""
    _, bu, bv, _ = hits
    sel = np.flatnonzero(owner[:, 0] == mesh)
    b = np.stack([1 - bu[sel] - bv[sel], bu[sel], bv[sel]], axis=1)[:, :, None]
    return sel, owner[sel, 1], b


def hit_uvs(tex: SkinTextures, tri_idx: NDArray[Any], b: NDArray[Any]) -> NDArray[np.float64]:
    """Texture coordinates (N, 2) of hits on ``tex``'s mesh: triangles ``tri_idx``,
    barycentrics ``b`` (N, 3, 1), as :func:`mesh_hits` gives them."""
    return (tex.uv[tex.uv_tris[tri_idx]] * b).sum(axis=1)


def times_albedo_power(rgb: NDArray[np.float32], albedo: NDArray[np.float32], power: float,
                       rows: int = 256) -> None:
    """``rgb *= albedo ** power`` in place (the albedo split's weights before and after
    the blur, d'Eon et al. 2007), a square root for 0.5 (the default) rather than a
    general power, in bands of ``rows`` rows: the whole texture's weights at once were
    201 MB of new memory at texture 4096, at the diffusion's peak."""
    for y in range(0, rgb.shape[0], rows):
        band = albedo[y:y + rows]
        rgb[y:y + rows] *= np.sqrt(band) if power == 0.5 else np.power(band, power)


def times_albedo_weight(rgb: NDArray[np.float32], albedo: NDArray[np.float32] | None,
                        image: NDArray[np.float32] | None, power: float) -> None:
    """``rgb *= albedo ** power`` in place from the albedo map where one was made
    (:func:`times_albedo_power`), else from the albedo's own image on the device
    (:func:`~.resample.times_resampled_power`: the same floats for the powers of
    :data:`~.resample.EXACT_POWERS`, the only ones a render asks of it without a map)."""
    if albedo is not None:
        times_albedo_power(rgb, albedo, power)
    else:
        assert image is not None
        times_resampled_power(rgb, image, power)


def surface_flux(rgb: NDArray[np.float32], maps: TextureMaps, rows: int = 256) -> float:
    """The flux of a texture of irradiance or radiance exitance ``rgb`` (H, W, 3) over its
    charts, summed over channels: sum of value x texel area in mm^2 (mm per texel along u
    times along v) x coverage. In bands of ``rows`` rows: the areas of the whole texture
    at once were 67 MB of new memory at texture 4096, at the diffusion's peak."""
    def flux(band: slice) -> float:
        area = maps.texel_area_mm2(band) * maps.coverage[band]
        return float((area.ravel() @ rgb[band].reshape(-1, 3)).sum(dtype=np.float64))

    total = 0.0
    for part in in_bands(flux, rgb.shape[0], rows):  # on the cores; added in band order
        total += part
    return total


class _BothArrived:
    """Calls ``then`` once both the irradiance and the layout have arrived (each counts
    once, from any thread)."""

    def __init__(self, then: Callable[[], None]) -> None:
        self._then = then
        self._lock = threading.Lock()
        self._waiting = {"irradiance", "layout"}

    def arrive(self, party: str) -> None:
        with self._lock:
            if party not in self._waiting:
                return
            self._waiting.discard(party)
            last = not self._waiting
        if last:
            self._then()


@dataclass
class TaskLog:
    seconds: dict[str, float] = field(default_factory=dict)
    cached: list[str] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    measures: dict[str, Any] = field(default_factory=dict)


class CameraHits(NamedTuple):
    """What a render's camera sees (:meth:`Renderer._camera_hits`): rays through the
    pixel centres (origins, unit directions) and their first hits (triangle or -1,
    barycentric u, v, distance), the silhouette pixels' flat indices and their extra
    rays and hits."""

    origins: NDArray[np.float64]
    dirs: NDArray[np.float64]
    hits: tuple[NDArray[Any], ...]
    edge: NDArray[np.intp]
    edge_origins: NDArray[np.float64]
    edge_dirs: NDArray[np.float64]
    edge_hits: tuple[NDArray[Any], ...]


@dataclass
class SkinTextures:
    """Texture-space results of one skin mesh."""

    mesh: SceneMesh
    uv: NDArray[np.float64]
    uv_tris: NDArray[np.int32]
    tris: NDArray[np.int32]
    maps: TextureMaps
    albedo: NDArray[np.float32] | None = None
    """The albedo map (:func:`albedo_texture`), made only for a split whose powers
    :func:`~.resample.times_resampled_power` does not take as numpy does
    (:meth:`Renderer._albedo`)."""
    albedo_image: NDArray[np.float32] | None = None
    """The albedo's own image (:func:`albedo_image`; after the irradiance, which does not
    read it): the split's weights and the shading's lookups are made from it, the same
    floats as from the map, without the map (201 MB at texture 4096)."""
    irradiance_filled: NDArray[np.float32] | None = None  # seams filled, for lookups
    visibility: dict[str, NDArray[np.float32]] = field(default_factory=dict)
    radiance: NDArray[np.float32] | None = None
    period: int = 2
    """The interleaving period of its shadow rays (:meth:`Renderer._interleaving`)."""
    texels_per_pixel: float = 0.0
    """Texels across an image pixel at the skin (:func:`texels_per_pixel`; 0: unknown)."""
    keys: dict[str, str] = field(default_factory=dict)
    """Cache keys of the texture maps, albedo and irradiance: what later tasks key on,
    instead of hashing the maps themselves."""
    at_hits: dict[str, dict[str, NDArray[np.float32]]] | None = None
    """The irradiance (N, 3), the albedo (N, 3) and each light's visibility (N,) looked up
    at the camera's hits on this mesh, 'center' and 'edge' rays
    (:meth:`Renderer._look_up_at_hits`; what the AOVs asked for need):
    taken before the diffusion in a render's last frame, so that the maps could go
    (None: the shading looks them up in the maps)."""
    hit_uv: dict[str, NDArray[np.float64]] = field(default_factory=dict)
    """The texture coordinates of those hits, by part, where they were taken: the
    shading reads them rather than making them again."""

    def albedo_map(self) -> NDArray[np.float32]:
        """The albedo map: the one made, else one made now from the image."""
        if self.albedo is not None:
            return self.albedo
        assert self.albedo_image is not None
        return albedo_texture(self.albedo_image, self.maps.triangle.shape[0])

    @property
    def irradiance(self) -> NDArray[np.float32] | None:
        """The irradiance (H, W, 3), 0 off the charts, as a new array: the filled one where
        a triangle covers the texel, which the push-pull and the gutter leave as it was
        (a copy kept beside the filled one held 201 MB at texture 4096)."""
        filled = self.irradiance_filled
        if filled is None:
            return None
        triangle = self.maps.triangle
        out = np.empty(filled.shape, np.float32)

        def band(rows: slice) -> None:  # in bands on the cores: 0.30 -> 0.14 s at 4096
            np.copyto(out[rows], np.where((triangle[rows] >= 0)[..., None], filled[rows],
                                          np.float32(0.0)))

        in_bands(band, out.shape[0], BAND_ITEMS // max(out.shape[1], 1))
        return out


class Renderer:
    """Renders frames of a stage; texture-space work is cached across frames and edits."""

    def __init__(self, stage: Any, options: RenderOptions,
                 progress: Callable[[str], None] | None = None) -> None:
        self.stage = stage
        self.options = options
        if options.device:
            set_device(options.device)
        self.delegate = SceneDelegate(stage, options.camera)
        self.progress = progress or (lambda _msg: None)
        # large buffers ask for huge pages only where their first touch is not dearer
        # (huge_pages); numpy's arrays too, unless the user set numpy's own switch
        self.huge_pages = huge_pages_choice()
        if not self.huge_pages.use and "NUMPY_MADVISE_HUGEPAGE" not in os.environ:
            apply_to_numpy(False)
        self._cache: dict[str, Any] = {}
        self._cache_lock = threading.Lock()  # the diffusion layout's task runs on a thread
        self.textures: list[SkinTextures] = []
        self._prewarmed = False
        self.last_frame = False
        """Whether no frame follows this one (:func:`render_files`' last): its texture
        maps' position and normal, and its seam layout's surface, go as soon as its
        irradiance and layout are made, rather than stay for a next frame."""

    def close(self) -> None:
        self.delegate.close()

    def clear_cache(self) -> None:
        """Drop every cached task result (texture-space maps, irradiance, diffusion, and
        the diffusion layout's device buffers): the next frame recomputes them."""
        self._cache.clear()

    def _cached(self, log: TaskLog, task: str, key: str, compute: Callable[[], Any],
                report: bool = True) -> Any:
        """``compute()``'s value, kept under ``task`` and ``key`` for later frames (one
        generation per task); ``report``: name the task to the progress callback."""
        full = f"{task}:{key}"
        with self._cache_lock:
            if full in self._cache:
                log.cached.append(task)
                return self._cache[full]
        if report:
            self.progress(task)
        start = time.perf_counter()
        value = compute()
        log.seconds[task] = log.seconds.get(task, 0.0) + time.perf_counter() - start
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith(f"{task}:")]:
                del self._cache[k]  # one generation per task: memory stays bounded
            self._cache[full] = value
        return value

    # ---- texture-space tasks
    def _uvs(self, log: TaskLog, mesh: SceneMesh) -> tuple[NDArray[Any], NDArray[np.int32]]:
        why = usable_uvs(mesh)
        if why is None:
            return mesh.uv, uv_triangles(mesh)  # type: ignore[return-value]

        def compute() -> tuple[NDArray[Any], NDArray[np.int32]]:
            uv, uv_tris, measures = unwrap_and_write_back(
                self.stage, mesh, why, self.options.write_uvs, self.progress)
            log.measures["unwrap"] = measures
            return uv, uv_tris

        return self._cached(log, "unwrap", mesh.geometry_key(), compute)

    def _kernel_plan(self, scene: SceneData) -> list[Callable[[], Any]]:
        """The device kernels this render will need, in the order it needs them, for a
        :class:`~.opencl.Prewarm` to build and compile while the host works."""
        opts = self.options
        domes = [lt.path for lt in scene.lights if lt.kind == "dome" and lt.texture]
        # each skin mesh's interleaving period where its UVs are known before the render
        # (an unwrap's are not: theirs, if not 2, are built at their first launch)
        periods = {self._interleaving(scene, m, m.uv, uv_triangles(m), triangulate(m.mesh))[0]
                   if usable_uvs(m) is None else 2 for m in scene.skin}
        steps: list[Callable[[], Any]] = [
            texture_kernels,
            *(partial(irradiance_kernels, scene.lights, opts.light_samples,
                      opts.shadow_sampling != "full", domes,
                      filtered=opts.shadow_sampling == "interleaved",
                      sequence=opts.light_sequence,
                      refined=opts.shadow_sampling == "adaptive", period=p)
              for p in sorted(periods)),
            push_pull_kernels]
        if opts.scattering and opts.blur == "recursive":
            steps.insert(1 + len(periods), margin_kernels)  # the seam layout's
            regions = sorted({0 if m.region_weights is None else m.region_weights.shape[1]
                              for m in scene.skin})
            steps += [partial(pyramid_kernels, r) for r in regions] + [seam_read_kernel]
            stream = streams(opts.texture_size ** 2 * 16)
            # the finest level, the coarser ones (smaller: plain stores), the switch's
            steps += [partial(pass_kernels, s) for s in dict.fromkeys((stream, False,
                                                                       TUNE_STREAM))]
            steps += [tuning_kernels, partial(texel_kernels, stream)]
        return steps

    def _textures(self, log: TaskLog, scene: SceneData, mesh: SceneMesh) -> SkinTextures:
        opts = self.options
        uv, uv_tris = self._uvs(log, mesh)
        tris = triangulate(mesh.mesh)
        key = content_hash(mesh.mesh.points, tris, uv, uv_tris, mesh.region_weights
                           if mesh.region_weights is not None else 0, opts.texture_size,
                           scene.meters_per_unit)
        maps = self._cached(log, "texture_maps", key, lambda: rasterize(
            mesh.mesh.points, tris, uv, uv_tris, opts.texture_size, scene.meters_per_unit,
            mesh.region_weights))
        albedo_key = content_hash(key, mesh.albedo, scene.working_colorspace)
        period, per_pixel = self._interleaving(scene, mesh, uv, uv_tris, tris)
        irradiance_key = content_hash(
            mesh.geometry_key(), opts.texture_size, scene_geometry_key(scene),
            [lt.key() for lt in scene.lights], opts.light_samples, opts.roughness, opts.rho_s,
            opts.seed, opts.shadow_sampling, opts.light_sequence,
            period if opts.shadow_sampling != "full" else 0)  # full sampling has none
        return SkinTextures(mesh, uv, uv_tris, tris, maps, period=period,
                            texels_per_pixel=per_pixel,
                            keys={"maps": key, "albedo": albedo_key,
                                  "irradiance": irradiance_key})

    def _interleaving(self, scene: SceneData, mesh: SceneMesh, uv: NDArray[Any],
                      uv_tris: NDArray[Any], tris: NDArray[Any]) -> tuple[int, float]:
        """The interleaving period of a skin mesh's shadow rays
        (:func:`~.lighting.interleave_period` of its texels per pixel, or up to the
        option's period) and its texels per pixel (0 without a camera)."""
        opts = self.options
        per_pixel = 0.0 if scene.camera is None else texels_per_pixel(
            mesh.mesh.points, tris, uv, uv_tris, opts.texture_size, scene.camera,
            opts.resolution[0])
        points = sobol_points(opts.light_samples) if opts.light_sequence == "sobol" \
            else opts.light_samples
        return interleave_period(per_pixel, points, opts.interleave_period), per_pixel

    def _albedo(self, log: TaskLog, scene: SceneData, tex: SkinTextures) -> None:
        """``tex``'s albedo image and, where the split's weights need it, its map (a
        split of 0.5, the default, does not): after the irradiance, which does not read
        them (a painted albedo's map held 201 MB beside the irradiance's peak at texture
        4096; making it took 0.4 s)."""
        key = tex.keys["albedo"]
        image, source = self._cached(log, "albedo", key, lambda: albedo_image(
            tex.mesh, scene.working_colorspace))
        log.measures["albedo_source"] = source
        tex.albedo_image = image
        a = self.options.albedo_split
        if a not in EXACT_POWERS or 1.0 - a not in EXACT_POWERS:
            tex.albedo = self._cached(log, "albedo_map", key, lambda: albedo_texture(
                image, self.options.texture_size))

    def _irradiance(self, log: TaskLog, scene: SceneData, tex: SkinTextures,
                    rays: RayScene, dome_textures: dict[str, NDArray[np.float32]],
                    release: _BothArrived | None = None,
                    after_rays: Callable[[], None] | None = None) -> None:
        """``tex``'s irradiance and visibility maps. In a render's last frame
        (``release``) the position and normal maps go once the texels' rows are taken
        and the seam layout beside needs them no more (:meth:`_release_maps`): 0.4 GB
        at texture 4096 that the rays' peak held; the filter reads a normal map made
        again from the rows (:func:`normal_map`). ``after_rays`` is called once the
        shadow rays are cast (not at all where the maps come from the cache)."""
        opts = self.options
        maps = tex.maps
        covered = maps.triangle >= 0
        key = tex.keys["irradiance"]
        period = tex.period

        def compute() -> Any:
            nonlocal maps
            # covered texels by flat index and np.take / np.put: a boolean mask over
            # (H, W, 3) maps gathers and scatters rows several times slower. In blocks,
            # so that their rays go to Embree in a coherent order as they are
            texel = texels_in_blocks(covered)
            interleave = np.take(interleave_classes(covered.shape, period), texel) \
                if opts.shadow_sampling != "full" else None
            positions, normals = (texel_rows(m, texel) for m in maps.surface)
            if release is not None:
                maps = maps.without_surface(*self._keeps())
                release.arrive("irradiance")
            res = irradiance_texture(positions, normals, scene.lights, rays,
                                     opts.light_samples, opts.roughness, opts.rho_s,
                                     opts.seed, dome_textures, interleave, opts.light_sequence,
                                     coherent=True, period=period)
            penumbra: dict[str, int] = {}  # texels refined per light (adaptive)
            if opts.shadow_sampling == "adaptive" and res.interleaved:
                res, refined = refine_penumbrae(
                    res, covered, positions, normals, interleave, scene.lights, rays,
                    opts.light_samples, opts.roughness, opts.rho_s, opts.seed, dome_textures,
                    opts.light_sequence, texel, coherent=True, period=period)
                penumbra = {path: int(where.size) for path, where in refined.items()}
            if after_rays is not None:
                after_rays()
            visibility = res.visibility
            filtered = bool(interleave is not None and res.interleaved and visibility)
            normal = None if not filtered or maps.normal is not None else \
                normal_map(normals, texel, covered.shape)
            # the rays are cast: the points go before the filter's planes (0.18 GB at
            # texture 4096)
            del positions, normals
            # the gutter's sources on a thread beside the filter and the planes, whose
            # numpy steps leave a core idle (0.2-0.3 s at texture 4096 on the main one)
            coverage = maps.coverage  # made here, not there
            gutter = beside(lambda: prepare_dilation(coverage), "skinpipe-gutter")
            if filtered:  # the sums of the visibility as traced are not made at all
                visibility = interleaved_visibility(res, maps, texel, period, normal)
                entering = res.entering_with(visibility)
            else:
                entering = res.entering
            del normal
            notes = (res.skipped, res.rays, res.seconds, penumbra)
            # the per-light sums go before the planes and their push-pull (0.3 GB at
            # texture 4096)
            del interleave, res
            # one push-pull fills the irradiance and the visibility the specular lobe
            # looks up (dome lights light it unshadowed: theirs is not needed)
            kinds = {lt.path: lt.kind for lt in scene.lights}
            spec = [p for p in visibility if kinds.get(p) != "dome"]
            planes = np.zeros((*covered.shape, 3 + len(spec)), np.float32)
            flat = planes.reshape(-1, planes.shape[-1])
            columns = [visibility[path] for path in spec]

            def scatter(rows: slice) -> None:  # on the cores: 0.3 s of one -> 0.12 of two
                at = texel[rows]
                flat[at, :3] = entering[rows]  # by flat index: a strided mask's took 5x
                for i, column in enumerate(columns):
                    flat[at, 3 + i] = column[rows]

            in_bands(scatter, texel.size)
            pulled = push_pull(planes, maps.coverage, in_place=True)
            gutter.result()
            filled = dilate_charts(pulled, maps.coverage)
            vis = {path: filled[..., 3 + i] for i, path in enumerate(spec)}
            # the cache keeps what later tasks read, not the per-light arrays (~100 MB);
            # the irradiance itself is the filled one on the charts (SkinTextures)
            return filled[..., :3], vis, notes

        filled, vis, (skipped, rays_cast, seconds, penumbra) = self._cached(
            log, "irradiance", key, compute)
        if opts.interleave_period and period != opts.interleave_period and \
                opts.shadow_sampling != "full":
            skipped = [*skipped, f"interleave period {opts.interleave_period}: "
                       f"{opts.light_samples} light samples cannot give each of its "
                       f"{opts.interleave_period ** 2} classes one; period {period}"]
        tex.irradiance_filled, tex.visibility = filled, vis
        log.skipped += [s for s in skipped if s not in log.skipped]
        log.measures["irradiance"] = {"rays": rays_cast, "seconds": seconds,
                                      "mrays_per_s": rays_cast / max(seconds, 1e-9) / 1e6,
                                      "rays_per_texel": rays_cast / max(int(covered.sum()), 1),
                                      "penumbra_texels": penumbra,
                                      "interleave_period": period if opts.shadow_sampling
                                      != "full" else None,
                                      "texels_per_pixel": round(tex.texels_per_pixel, 3)}

    @staticmethod
    def _hit_uvs(scene: SceneData, tex: SkinTextures, cam: CameraHits,
                 owners: dict[str, NDArray[Any]]) -> dict[str, NDArray[np.float64]]:
        """The texture coordinates of the camera's hits on ``tex``'s mesh, by part
        ('center', 'edge'); ``owners``: each part's :func:`ray_owners`."""
        mesh = scene.meshes.index(tex.mesh)
        return {part: hit_uvs(tex, *mesh_hits(owners[part], hits, mesh)[1:])
                for part, hits in (("center", cam.hits), ("edge", cam.edge_hits))}

    def _look_up_at_hits(self, tex: SkinTextures, uvs: dict[str, NDArray[np.float64]]
                         ) -> None:
        """``tex.at_hits``: what the shading reads of the irradiance and the lights'
        visibility maps (their push-pulled planes: 268 MB at texture 4096 with one
        shadowed light) at the camera's hits on ``tex``'s mesh (:meth:`_hit_uvs`, kept in
        ``tex.hit_uv`` for the shading), the same bilinear lookups, so that the diffusion
        lets the maps go once it has read the irradiance (:meth:`_release_irradiance`)
        rather than hold them through its peak."""
        tex.hit_uv.update(uvs)
        tex.at_hits = {part: self._irradiance_lookups(tex, uv) for part, uv in uvs.items()}

    def _irradiance_lookups(self, tex: SkinTextures, uv: NDArray[Any]
                            ) -> dict[str, NDArray[np.float32]]:
        """What the shading reads of ``tex``'s irradiance ('irradiance', (N, 3), for its
        AOV), albedo ('albedo', (N, 3), likewise) and each light's visibility (by light
        path, (N,), for the specular lobe) at texture coordinates ``uv`` (N, 2): the AOVs
        asked for need, bilinear lookups in the push-pulled maps and the albedo's (made
        from its image where the map was not made)."""
        wanted = set(self.options.aovs)
        got: dict[str, NDArray[np.float32]] = {}
        if "albedo" in wanted:
            assert tex.albedo_image is not None
            size = self.options.texture_size
            got["albedo"] = bilinear_of(albedo_texels(tex.albedo_image, size), (size, size),
                                        uv)
        if "irradiance" in wanted:
            assert tex.irradiance_filled is not None
            got["irradiance"] = bilinear(tex.irradiance_filled, uv)
        if wanted & {"beauty", "specular"}:
            for path, plane in tex.visibility.items():
                got[path] = bilinear(plane, uv)[:, 0]
        return got

    def _release_albedo(self, tex: SkinTextures) -> None:
        """Let ``tex``'s albedo map go (out of the cache too: a later render makes it
        again) once its weight before the blur is taken and the shading's lookups of it
        (:meth:`_look_up_at_hits`); its image stays for the weight after the blur
        (:func:`~.resample.times_resampled_power`)."""
        with self._cache_lock:
            self._cache.pop(f"albedo_map:{tex.keys['albedo']}", None)
        tex.albedo = None

    def _release_irradiance(self, tex: SkinTextures) -> None:
        """Let ``tex``'s filled irradiance and visibility maps go (out of the cache too:
        a later render makes them again) once the shading's lookups of them are taken
        (:meth:`_look_up_at_hits`) and the diffusion has read the irradiance."""
        with self._cache_lock:
            self._cache.pop(f"irradiance:{tex.keys['irradiance']}", None)
        tex.irradiance_filled, tex.visibility = None, {}

    def _release_maps(self, tex: SkinTextures) -> None:
        """Let ``tex``'s position and normal maps go (and the stretch and region maps,
        :meth:`_keeps`) in a render's last frame, once the irradiance has taken its
        texels' rows and the seam layout beside needs them no more (0.4-0.7 GB at
        texture 4096): out of the cache too, so that a later render makes them again.
        Safe from the layout's thread (:class:`_BothArrived`)."""
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith("texture_maps:")]:
                del self._cache[k]
            tex.maps = tex.maps.without_surface(*self._keeps())

    def _release_layout(self, layout: DiffusionLayout) -> None:
        """Let a last frame's seam layout's surface go once its tiles are made
        (:meth:`~.diffusion.DiffusionLayout.release_surface`; out of the cache: it makes
        no tiles any more)."""
        with self._cache_lock:
            for k in [k for k in self._cache if k.startswith("diffusion_layout:")]:
                del self._cache[k]
            layout.release_surface()

    def _release_surface(self, tex: SkinTextures, layout: DiffusionLayout | None) -> None:
        """:meth:`_release_maps` and :meth:`_release_layout` (each again a no-op)."""
        self._release_maps(tex)
        if layout is not None:
            self._release_layout(layout)

    def _keeps(self) -> tuple[bool, bool]:
        """Whether a last frame's maps keep their stretch maps and their region weights
        past the irradiance: both for the gather blur, which reads them, and each for
        its texture output (the recursive blur's layout makes the region weights again
        per texel, :class:`~.texture_maps.TexelRegions`)."""
        opts = self.options
        gather = opts.blur == "gather"
        return (gather or "stretch" in opts.texture_outputs,
                gather or "region" in opts.texture_outputs)

    def _terms(self, tex: SkinTextures) -> tuple[DiffusionTerms, float]:
        """The blur schedule of a skin mesh's fits at its texture's median texel size
        (mm), which it returns too."""
        maps, opts = tex.maps, self.options
        texel_mm = float(np.median(np.sqrt(maps.mm_per_texel_u * maps.mm_per_texel_v)[
            maps.triangle >= 0]))
        # blurs narrower than half a texel change nothing a texture can hold
        return kept_diffusion_terms(tex.mesh.fits, opts.variance_grid, opts.single_profile,
                                    floor_mm2=(0.5 * texel_mm) ** 2), texel_mm

    def _diffusion_key(self, tex: SkinTextures, terms: DiffusionTerms) -> str:
        opts = self.options
        return content_hash(tex.keys["irradiance"], tex.keys["albedo"], terms.variances_mm2,
                            terms.weights, opts.albedo_split, opts.scattering, opts.blur)

    def _layout_beside(self, log: TaskLog, tex: SkinTextures, terms: DiffusionTerms,
                       rays: RayScene, mesh_index: int, geometry_key: str,
                       release: _BothArrived | None = None
                       ) -> Future[DiffusionLayout] | None:
        """The diffusion layout's task for a recursive blur, started on a thread to run
        beside the irradiance (None for other blurs): it reads only the texture maps and
        the ray scene, and each leaves the cores idle part of the time (single-threaded
        numpy steps, waits for the device) that the other fills. The demo scene's render,
        old and new in turns: texture 2048 19.5-20.8 -> 18.6-19.0 s, 4096 61.9-69.2 ->
        53.4-61.7 s (peak RSS 6.40-6.56 -> 6.48-7.03 GB); 1024 unchanged.

        The layout depends on the UV layout and the geometry only: it is made once for
        every frame, light and set of terms (a task of its own, cached); the charts'
        tiles cross the UV seams (chart_tiles), each set of terms adds the tiles and
        margins it reaches (prepare). A cached layout that holds the terms' tiles is
        back at once. With ``options.layout_cache`` the tiles come from disk where an
        earlier process made them (:mod:`.tile_store`), and go there where this one
        makes them; ``render.json``'s ``tile_store`` says which.

        The layout reads no position or normal map: where it makes tiles it makes the
        surface at its margins' start texels from the triangles
        (:class:`~.texture_maps.TexelSurface`). In a render's last frame (``release``) it
        says so once it holds the maps less their surface, so that they may go as soon
        as the irradiance has taken its texels' rows (:meth:`_release_maps`), and its own
        surface goes as it ends."""
        opts = self.options
        if not (opts.scattering and opts.blur == "recursive") or \
                f"diffusion:{self._diffusion_key(tex, terms)}" in self._cache:
            return None  # a gather blur needs none; a cached diffusion needs none now

        key = content_hash(tex.keys["maps"], geometry_key, mesh_index)

        def layout(maps: TextureMaps, store: TileStore | None) -> DiffusionLayout:
            return DiffusionLayout(maps.mm_per_texel_u, maps.mm_per_texel_v, maps.coverage,
                                   maps.region_weights,
                                   chart_layout(maps, tex.mesh.mesh.points, tex.tris, tex.uv,
                                                tex.uv_tris, rays, mesh_index),
                                   store, maps.texel_regions,
                                   maps.triangle_stretch() if maps.tri_mm is not None
                                   else None)

        def make() -> DiffusionLayout:
            try:
                # the maps less their surface, taken before it says it needs no more of
                # them: once made, the layout reads no map but the triangle map (its
                # surface and texel sizes come from the triangles)
                maps = tex.maps.without_surface()
                if release is not None:
                    release.arrive("layout")
                store = None if opts.layout_cache is None else \
                    TileStore(Path(opts.layout_cache), key)
                prepared = self._cached(log, "diffusion_layout", key,
                                        partial(layout, maps, store), report=False)
                del maps
                # other terms (one profile for every region) add the tiles they lack
                start = time.perf_counter()
                prepared.prepare(terms.variances_mm2)
                log.seconds["diffusion_layout"] = (log.seconds.get("diffusion_layout", 0.0)
                                                   + time.perf_counter() - start)
                if release is not None:
                    self._release_layout(prepared)
                return prepared
            finally:
                if release is not None:
                    release.arrive("layout")

        return beside(make, "skinpipe-layout")

    def _diffusion(self, log: TaskLog, tex: SkinTextures, terms: DiffusionTerms,
                   texel_mm: float, layout: Future[DiffusionLayout] | None) -> None:
        opts = self.options
        assert tex.irradiance_filled is not None
        key = self._diffusion_key(tex, terms)
        prepared: DiffusionLayout | None = None
        if layout is not None:
            if not layout.done():
                self.progress("diffusion_layout")
            start = time.perf_counter()
            prepared = layout.result()
            log.measures["diffusion_layout"] = {
                "beside": "irradiance", "waited_s": time.perf_counter() - start}
        if self.last_frame:
            self._release_surface(tex, prepared)
        maps = tex.maps  # after the release: not the maps that still hold the surface

        albedo = tex.albedo  # None: the weights come from its image

        def compute() -> Any:
            nonlocal albedo
            a = opts.albedo_split
            pre = tex.irradiance  # a new array: weighted in place
            assert pre is not None
            if tex.at_hits is not None:  # the shading's lookups are taken
                self._release_irradiance(tex)
            times_albedo_weight(pre, albedo, tex.albedo_image, a)
            if albedo is not None and tex.at_hits is not None and 1.0 - a in EXACT_POWERS:
                # the weight after the blur comes from the albedo's own image: the map
                # goes before the diffusion's peak (201 MB at texture 4096)
                albedo = None
                self._release_albedo(tex)
            # the heap the frame's earlier steps freed goes back to the system before
            # the diffusion's work buffers come (0.18 GB at texture 4096)
            release_freed_heap()
            cov = maps.coverage
            # the blur moves flux, it must not create or lose it (chart borders included)
            flux_in = surface_flux(pre, maps)
            skipped: list[str] = []
            if opts.scattering:
                if prepared is not None:
                    out, stats = diffuse_prepared(prepared, pre, terms.variances_mm2,
                                                  terms.weights)
                    if self.last_frame:  # its buffers stayed beside the push-pull's
                        prepared.release_work()
                else:
                    out, stats = diffuse_gather(pre, maps.mm_per_texel_u, maps.mm_per_texel_v,
                                                cov, terms.variances_mm2, terms.weights,
                                                maps.region_weights)
                del pre  # texture-sized arrays go as soon as they are used (peak memory)
                skipped, passes = stats.skipped, stats.passes
                work = {"pyramid_levels": stats.levels,
                        "full_resolution_blurs": stats.full_blurs}
            else:
                out, passes, work = pre, 0, {}
                skipped = ["diffusion: scattering off (texture-mapped irradiance only)"]
            flux_out = surface_flux(out, maps)
            energy = flux_out / flux_in if flux_in > 0 else 1.0
            times_albedo_weight(out, albedo, tex.albedo_image, 1.0 - a)  # out: its own
            out *= np.float32(1.0 / math.pi)
            radiance = dilate_charts(push_pull(out, cov, in_place=True), cov)
            return radiance, skipped, passes, energy, work

        radiance, skipped, passes, energy, work = self._cached(log, "diffusion", key, compute)
        tex.radiance = radiance
        log.skipped += [f"{tex.mesh.path}: {s}" for s in terms.notes + skipped]
        log.measures["diffusion"] = {
            "variances_mm2": terms.variances_mm2.tolist(),
            "blur": opts.blur,
            "blur_passes": passes,
            **work,
            "energy_ratio": energy,
            "grid_error_eq2c": terms.error,
            "mm_per_texel_median": texel_mm,
        }

    def texture_space(self, log: TaskLog, scene: SceneData, mesh: SceneMesh, rays: RayScene,
                      dome_textures: dict[str, NDArray[np.float32]] | None = None,
                      camera: Callable[[], tuple[CameraHits, dict[str, NDArray[Any]]]]
                      | None = None
                      ) -> SkinTextures:
        """A skin mesh's texture-space tasks for a frame of ``scene`` (the ray scene
        ``rays`` holds every mesh of it): texture maps, irradiance, albedo and the
        diffused radiance, the seam layout made beside the irradiance; each task's
        seconds, cached tasks and measures go to ``log``. With ``camera`` (which gives the
        camera's hits and, per part, their :func:`ray_owners`), a last frame that writes no
        irradiance texture looks the irradiance and visibility up at the hits before the
        diffusion and lets the maps go (:meth:`_look_up_at_hits`)."""
        tex = self._textures(log, scene, mesh)
        terms, texel_mm = self._terms(tex)
        # a last frame lets the maps the irradiance and the layout read go once both are
        # done with them
        release = _BothArrived(lambda: self._release_maps(tex)) if self.last_frame else None
        layout = self._layout_beside(log, tex, terms, rays, scene.meshes.index(mesh),
                                     scene_geometry_key(scene), release)
        if layout is None and release is not None:
            release.arrive("layout")
        look_up = camera is not None and self.last_frame and \
            "irradiance" not in self.options.texture_outputs
        uvs: list[Future[dict[str, NDArray[np.float64]]]] = []

        def hit_uvs() -> dict[str, NDArray[np.float64]]:
            assert camera is not None
            return self._hit_uvs(scene, tex, *camera())

        try:
            # the camera's rays and the hits' uvs need no irradiance: on a thread once the
            # rays are cast, while the filter's numpy steps leave a core idle (0.2 s of the
            # main thread at texture 4096)
            self._irradiance(log, scene, tex, rays, dome_textures or {}, release,
                             (lambda: uvs.append(beside(hit_uvs, "skinpipe-camera")))
                             if look_up else None)
        except BaseException:
            # no thread outlives its frame, not even on errors
            wait([*uvs, *([] if layout is None else [layout])])
            raise
        self._albedo(log, scene, tex)
        if look_up:
            self._look_up_at_hits(tex, uvs[0].result() if uvs else hit_uvs())
        self._diffusion(log, tex, terms, texel_mm, layout)
        store = None if layout is None else layout.result().store
        if store is not None:  # its writes ran beside the diffusion
            store.flush()
            log.measures["tile_store"] = store.summary()
        return tex

    # ---- per frame
    def render(self, time_code: Any = None) -> tuple[dict[str, NDArray[np.float32]], TaskLog]:
        """One frame: AOV images (H, W, 4 for beauty with alpha; H, W, 3 otherwise)."""
        log = TaskLog()
        t0 = time.perf_counter()
        scene = self.delegate.sync(time_code)
        log.seconds["sync"] = time.perf_counter() - t0
        if not scene.meshes:
            raise InputError("the stage has no visible mesh to render")
        if not scene.skin:
            raise InputError("no mesh with skin profiles (SkinProfileRegionsAPI + skin:profiles)"
                             " on the stage")
        if not scene.lights:
            raise InputError("the stage has no UsdLux light (DistantLight, SphereLight, "
                             "RectLight or DomeLight): nothing would be lit")
        if scene.camera is None:
            raise InputError("the stage has no UsdGeomCamera (add one, or pass --camera)")
        if not self._prewarmed:  # later frames find every kernel built
            start_prewarm(self._kernel_plan(scene))
            self._prewarmed = True
        rays = self._cached(log, "bvh", scene_geometry_key(scene), lambda: RayScene(
            [(m.mesh.points, triangulate(m.mesh)) for m in scene.meshes]))
        domes = {}
        for light in scene.lights:
            if light.kind == "dome" and light.texture:
                domes[light.path] = self._cached(log, f"dome:{light.path}", str(light.texture),
                                                 lambda lt=light: read_image(lt.texture).pixels)
        seen = [i for i, m in enumerate(scene.meshes) if m.camera_visible]
        if not seen:
            raise InputError("every mesh on the stage is hidden from the camera")
        camera_rays = rays
        if len(seen) < len(scene.meshes):  # occluders that only cast shadows
            def build() -> RayScene:
                view = RayScene([(scene.meshes[i].mesh.points,
                                  triangulate(scene.meshes[i].mesh)) for i in seen])
                view.owner[:, 0] = np.asarray(seen)[view.owner[:, 0]]  # scene's mesh index
                return view
            camera_rays = self._cached(log, "bvh_camera", content_hash(
                scene_geometry_key(scene), seen), build)
            log.skipped.append("camera rays: " + ", ".join(
                m.path for m in scene.meshes if not m.camera_visible) + " cast shadows only")
        # the last frame's texture-space results, for outputs; the camera's hits are
        # made where a last frame looks up what it needs of the irradiance there, before
        # the diffusion (Renderer._look_up_at_hits): made first, they waited for the
        # kernels' prewarm (0.5-0.8 s against 0.16 at texture 4096)
        made: list[tuple[CameraHits, dict[str, NDArray[Any]]]] = []
        making = threading.Lock()

        def camera() -> tuple[CameraHits, dict[str, NDArray[Any]]]:
            """The camera's hits and each part's (mesh, triangle) of them: once a frame
            (the log counts the task once), for the lookups and the shading; from any
            thread (a caller waits for one that is making them)."""
            with making:
                if not made:
                    cam = self._camera_hits(scene, log, camera_rays)
                    made.append((cam, {part: ray_owners(camera_rays, hits[0]) for part, hits
                                       in (("center", cam.hits), ("edge", cam.edge_hits))}))
            return made[0]

        skins = self.textures = [self.texture_space(log, scene, mesh, rays, domes, camera)
                                 for mesh in scene.skin]
        self.progress("shade")
        t0 = time.perf_counter()
        images = self._shade(scene, skins, rays, log, *camera())
        log.seconds["shade"] = time.perf_counter() - t0
        log.measures["huge_pages"] = asdict(self.huge_pages)
        log.measures["rays"] = {"counts": rays.stats.rays,
                                "mrays_per_s": rays.stats.mrays_per_s()}
        return images, log

    def _camera_hits(self, scene: SceneData, log: TaskLog, camera_rays: RayScene
                     ) -> CameraHits:
        """The camera's rays through the pixel centres and their first hits, the
        silhouette pixels (a 3 x 3 neighbourhood with both geometry and background) and
        their :data:`EDGE_SAMPLES` rays and hits: the same for every render of one camera,
        image size and geometry (the demo's three renders, a relit shot), so cached."""
        width, height = self.options.resolution
        cam = scene.camera
        assert cam is not None

        def compute() -> CameraHits:
            origins, dirs = cam.rays(width, height)
            hits = camera_rays.intersect(origins, dirs)
            mask = (hits[0] >= 0).reshape(height, width)
            padded = np.pad(mask, 1, mode="edge")
            windows = [padded[dy:dy + height, dx:dx + width]
                       for dy in range(3) for dx in range(3)]
            edge = np.flatnonzero((np.any(windows, axis=0) & ~np.all(windows, axis=0)).ravel())
            py, px = np.divmod(edge, width)
            offs = np.asarray(EDGE_SAMPLES)
            sx = (px[:, None] + 0.5 + offs[None, :, 0]).ravel()
            sy = (py[:, None] + 0.5 + offs[None, :, 1]).ravel()
            sub_origins, sub_dirs = cam.rays_at(sx, sy, width, height)
            return CameraHits(origins, dirs, hits, edge, sub_origins, sub_dirs,
                              camera_rays.intersect(sub_origins, sub_dirs))

        seen = [m.camera_visible for m in scene.meshes]
        return self._cached(log, "camera_hits", content_hash(
            cam.key(), width, height, scene_geometry_key(scene), seen), compute)

    def _shade(self, scene: SceneData, skins: list[SkinTextures], rays: RayScene,
               log: TaskLog, cam: CameraHits, owners: dict[str, NDArray[Any]]
               ) -> dict[str, NDArray[np.float32]]:
        """The AOV images: one camera ray through each pixel centre, and where a pixel's
        3 x 3 neighbourhood holds both geometry and background (a silhouette), the
        pixel is shaded again at :data:`EDGE_SAMPLES` (a rotated grid) and its alpha is
        their coverage, its colours their mean (premultiplied). ``owners``: each part's
        :func:`ray_owners` of the hits."""
        opts = self.options
        width, height = opts.resolution
        out, hit = self._shade_rays(scene, skins, rays, owners["center"], cam.origins,
                                    cam.dirs, cam.hits, log, "center")
        alpha = hit.astype(np.float32)
        edge = cam.edge
        if edge.size:
            sub, sub_hit = self._shade_rays(scene, skins, rays, owners["edge"],
                                            cam.edge_origins, cam.edge_dirs, cam.edge_hits,
                                            log, "edge")
            k = len(EDGE_SAMPLES)
            for a in AOVS:  # colours: the samples' mean; a region index stays the centre's
                out[a][edge] = sub[a].reshape(edge.size, k, 3).mean(axis=1)
            alpha[edge] = sub_hit.reshape(edge.size, k).mean(axis=1)
            log.measures["edge_pixels"] = {"pixels": int(edge.size), "samples": k}
        images = {}
        for a in opts.aovs:
            img = out[a].reshape(height, width, -1)
            if a == "beauty":
                img = np.concatenate([img, alpha.reshape(height, width, 1)], axis=2)
            images[a] = img
        skipped_aovs = [a for a in AOVS + DATA_AOVS if a not in opts.aovs]
        if skipped_aovs:
            log.skipped.append(f"AOVs not asked for: {', '.join(skipped_aovs)}")
        return images

    def _shade_rays(self, scene: SceneData, skins: list[SkinTextures], rays: RayScene,
                    owner: NDArray[Any], origins: NDArray[Any], dirs: NDArray[Any],
                    hits: tuple[NDArray[Any], ...], log: TaskLog, part: str
                    ) -> tuple[dict[str, NDArray[np.float32]], NDArray[np.bool_]]:
        """The AOVs asked for (the others stay zero) for camera rays (origins, dirs) and
        their ``hits`` among the meshes the camera sees (``owner``: each hit's mesh and
        triangle, :func:`ray_owners`; shadow rays against ``rays``, every mesh), and which
        rays hit. ``part``: which of the camera's rays they are ('center' or 'edge'), for
        what was taken of them before (``at_hits``, ``hit_uv``)."""
        opts = self.options
        wanted = set(opts.aovs)
        prim, _, _, dist = hits
        n_pix = origins.shape[0]
        out = {a: np.zeros((n_pix, 3), np.float32) for a in AOVS}
        out["region"] = np.full((n_pix, 1), -1.0, np.float32)
        mesh_index = {m.path: i for i, m in enumerate(scene.meshes)}
        for m_i, mesh in enumerate(scene.meshes):
            sel, tri_idx, b = mesh_hits(owner, hits, m_i)
            if sel.size == 0:
                continue
            tris = triangulate(mesh.mesh)
            pos = origins[sel] + dirs[sel] * dist[sel, None]
            normals = self._cached(log, f"normals:{mesh.path}", mesh.geometry_key(),
                                   lambda m=mesh, t=tris: vertex_normals(m.mesh.points, t))
            n = (normals[tris[tri_idx]] * b).sum(axis=1)
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            view = -dirs[sel]
            # two-sided: a normal facing away from the camera is flipped
            flip = np.einsum("ij,ij->i", n, view) < 0
            n[flip] *= -1
            tex = next((s for s in skins if mesh_index[s.mesh.path] == m_i), None)
            if tex is None:
                self._shade_plain(scene, mesh, pos, n, sel, rays, out)
                continue
            uv = tex.hit_uv[part] if part in tex.hit_uv else hit_uvs(tex, tri_idx, b)
            # only the AOVs asked for (the demo's comparison renders ask for beauty alone:
            # the albedo, irradiance and region lookups were 0.35 s of a 1.1 s shade)
            if wanted & {"beauty", "diffuse"}:
                n_dot_v = np.clip(np.einsum("ij,ij->i", n, view), 0, 1)
                leave = (1.0 - specular_albedo(n_dot_v, opts.roughness, opts.rho_s))[:, None]
                assert tex.radiance is not None
                out["diffuse"][sel] = bilinear(tex.radiance, uv) * leave
            at = self._irradiance_lookups(tex, uv) if tex.at_hits is None else \
                tex.at_hits[part]
            if "albedo" in wanted:
                out["albedo"][sel] = at["albedo"]
            if "irradiance" in wanted:
                out["irradiance"][sel] = at["irradiance"]
            if "region" in wanted and mesh.region_weights is not None:
                weights = (mesh.region_weights[tris[tri_idx]] * b).sum(axis=1)
                out["region"][sel, 0] = np.argmax(weights, axis=1)
            if wanted & {"beauty", "specular"}:
                out["specular"][sel] = self._specular(scene, pos, n, view, at)
        out["beauty"] = out["diffuse"] + out["specular"]
        return out, prim >= 0

    def _specular(self, scene: SceneData, pos: NDArray[Any], n: NDArray[Any],
                  view: NDArray[Any], at: dict[str, NDArray[np.float32]]
                  ) -> NDArray[np.float32]:
        """The specular lobe of each light but domes at the hits ``pos`` (normals ``n``,
        towards the camera ``view``), shadowed by its visibility there (``at``: by light
        path, :meth:`_irradiance_lookups` of these hits)."""
        opts = self.options
        spec = np.zeros((pos.shape[0], 3))
        for light in scene.lights:
            if light.path not in at or light.kind == "dome":
                continue
            l_dir, e_perp = light_direction(light, pos)
            h = l_dir + view
            h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
            nl = np.einsum("ij,ij->i", n, l_dir)
            f = torrance_sparrow(nl, np.einsum("ij,ij->i", n, view), np.einsum("ij,ij->i", n, h),
                                 np.einsum("ij,ij->i", view, h), opts.roughness, opts.rho_s)
            vis = at[light.path]
            spec += (f * np.maximum(nl, 0) * vis)[:, None] * e_perp
        return spec.astype(np.float32)

    def _shade_plain(self, scene: SceneData, mesh: SceneMesh, pos: NDArray[Any],
                     n: NDArray[Any], sel: NDArray[Any], rays: RayScene,
                     out: dict[str, NDArray[np.float32]]) -> None:
        """Meshes without skin profiles: Lambertian in their constant colour, direct light
        from each light's centre with one shadow ray (dome lights: unshadowed ambient)."""
        albedo = np.asarray(mesh.albedo.constant, np.float32)
        e = np.zeros((pos.shape[0], 3))
        origins = offset_ray_origin(pos, n)
        for light in scene.lights:
            if light.kind == "dome":
                e += light.radiance * math.pi * 0.5
                continue
            l_dir, e_perp = light_direction(light, pos)
            nl = np.maximum(np.einsum("ij,ij->i", n, l_dir), 0)
            far = np.full(pos.shape[0], np.inf) if light.kind == "distant" else \
                np.linalg.norm(light.position - pos, axis=1) * (1 - 1e-4)
            lit = nl > 0
            blocked = np.zeros(pos.shape[0], bool)
            blocked[lit] = rays.occluded(origins[lit], l_dir[lit], np.minimum(far[lit], 1e30))
            e += (nl * ~blocked)[:, None] * e_perp
        out["diffuse"][sel] = albedo * e / math.pi
        out["albedo"][sel] = albedo
        out["irradiance"][sel] = e


def texture_space_images(tex: SkinTextures, which: tuple[str, ...]
                         ) -> dict[str, NDArray[np.float32]]:
    """The texture-space maps ``which`` (:data:`~.options.TEXTURE_OUTPUTS`) of one skin
    mesh, rows flipped so that row 0 is v = 1 (as a texture image), plus coverage."""
    maps = tex.maps
    covered = maps.triangle >= 0
    out: dict[str, NDArray[np.float32]] = {}
    if "irradiance" in which and tex.irradiance is not None:
        out["irradiance"] = tex.irradiance
    if "radiosity" in which and tex.radiance is not None:
        out["radiosity"] = (tex.radiance * np.float32(math.pi)) * covered[..., None]
    if "stretch" in which:
        out["stretch"] = np.stack([maps.mm_per_texel_u, maps.mm_per_texel_v], axis=-1)
    if "region" in which:
        region = np.full(covered.shape, -1.0, np.float32)
        if maps.region_weights is not None:
            region[covered] = np.argmax(maps.region_weights[covered], axis=-1)
        out["region"] = region[..., None]
    out["coverage"] = maps.coverage[..., None]
    return {k: np.ascontiguousarray(v[::-1], np.float32) for k, v in out.items()}


_TEXTURE_CHANNELS = {"irradiance": ("R", "G", "B"), "radiosity": ("R", "G", "B"),
                     "stretch": ("u_mm", "v_mm"), "region": ("id",), "coverage": ("A",)}


def write_texture_outputs(out_dir: Path, name: str, renderer: Renderer, working: str
                          ) -> list[str]:
    """``<name>_uv.exr`` (``<name>_uv_<mesh>.exr`` for each of several skin meshes) with
    the options' texture-space maps; their paths."""
    which = renderer.options.texture_outputs
    paths = []
    for tex in renderer.textures if which else []:
        images = texture_space_images(tex, which)
        suffix = "" if len(renderer.textures) == 1 else \
            "_" + Tf.MakeValidIdentifier(tex.mesh.path.strip("/").replace("/", "_"))
        names = [f"{k}.{c}" for k in images for c in _TEXTURE_CHANNELS[k]]
        exr = write_exr(out_dir / f"{name}_uv{suffix}.exr",
                        np.concatenate(list(images.values()), axis=2), working,
                        channel_names=tuple(names))
        paths.append(str(exr))
    return paths


def scene_geometry_key(scene: SceneData) -> str:
    return content_hash(*[m.geometry_key() for m in scene.meshes])


# ------------------------------------------------------------------------ outputs


def display_image(beauty: NDArray[Any], working: str, config_source: str
                  ) -> tuple[NDArray[np.float32], dict[str, str]]:
    """Display-referred pixels through the config's default display and view, of the
    colour itself (a premultiplied beauty with alpha is divided by its alpha first: the
    view transform is not linear, and applied to colour times coverage it brightened the
    demo face's 2526 silhouette pixels by 0.12 of the display's range on average, 0.46
    at most, once the PNG's straight alpha was taken off)."""
    config = ocio_config(config_source)
    src = check_colorspace(working, config_source)
    display = config.getDefaultDisplay()
    view = config.getDefaultView(display)
    transform = OCIO.DisplayViewTransform(src=src, display=display, view=view)
    proc = config.getProcessor(transform).getDefaultCPUProcessor()
    rgb = np.nan_to_num(beauty[..., :3].astype(np.float32), copy=False, nan=0.0, posinf=1e4)
    if beauty.shape[-1] == 4:
        alpha = beauty[..., 3:4]
        np.divide(rgb, alpha, out=rgb, where=alpha > 0)
    # in row bands on the cores: OCIO lets go of the GIL, and the default view's ACES 2.0
    # output transform took 0.45 s for a 768 x 768 image on one core (0.23 s on two); a
    # pixel's value does not depend on the band
    pixels = rgb.reshape(-1, 3)
    in_bands(lambda rows: proc.applyRGB(pixels[rows]), pixels.shape[0],
             -(-pixels.shape[0] // min(host_threads(), BAND_THREADS)))
    return np.clip(rgb, 0, 1), {"display": display, "view": view, "config": config_source}


def display_colorspace(config_source: str, display: str, view: str) -> str:
    """The colour space a display/view pair's output is encoded in. OCIO 2.2+ configs
    share views across displays and answer ``<USE_DISPLAY_NAME>``: the colour space
    named as the display itself (OCIO's rule for shared views)."""
    space = ocio_config(config_source).getDisplayViewColorSpaceName(display, view)
    return display if space == OCIO.OCIO_VIEW_USE_DISPLAY_NAME else space


def write_outputs(out_dir: Path, name: str, images: dict[str, NDArray[np.float32]],
                  working: str, config_source: str, half: bool = False) -> dict[str, Any]:
    """OUT/<name>.exr (one layer per AOV, colour space in the header; half float with
    ``half``, where no value exceeds half's range) and OUT/<name>.png."""
    channels, names = [], []
    for aov, img in images.items():
        chans = {4: ("R", "G", "B", "A"), 3: ("R", "G", "B"), 1: ("id",)}[img.shape[2]]
        channels.append(img)
        names += [c if aov == "beauty" else f"{aov}.{c}" for c in chans]
    stack = np.concatenate(channels, axis=2)
    if not np.all(np.isfinite(stack)):
        raise SkinpipeError(f"{name}: the render produced non-finite pixels")
    if half and np.abs(stack).max() > HALF_MAX:
        raise SkinpipeError(f"{name}: a pixel exceeds half float's range ({HALF_MAX}); "
                            "write float EXRs (leave out --half-float)")

    def preview() -> dict[str, Any]:
        disp, info = display_image(images["beauty"], working, config_source)
        alpha = images["beauty"][..., 3:4]
        # tagged with the display's colour space, so the PNG carries its sRGB chunk
        space = display_colorspace(config_source, info["display"], info["view"])
        # straight alpha, as PNG stores it: OpenImageIO is told so, or it divides again
        png = write_ldr(out_dir / f"{name}.png", np.concatenate([disp, alpha], axis=2), 8,
                        {"oiio:ColorSpace": space, "oiio:UnassociatedAlpha": 1,
                         "skinpipe:displayView": f"{info['display']} / {info['view']}"})
        return {"png": str(png), **info}

    # the PNG's display transform and writing on a thread beside the EXR's (OpenImageIO
    # and OCIO let Python's lock go): the demo scene's 1024 x 1024 frame 0.43-0.69 ->
    # 0.36-0.38 s
    with ThreadPoolExecutor(1, thread_name_prefix="skinpipe-png") as side:
        png = side.submit(preview) if "beauty" in images else None
        exr = write_exr(out_dir / f"{name}.exr", stack, working, channel_names=tuple(names),
                        half=half)
        result: dict[str, Any] = {"exr": str(exr), "colorspace": working}
        if png is not None:
            result.update(png.result())
    return result


def render_files(scene_path: Path, out_dir: Path, options: RenderOptions,
                 frames: tuple[int, int] | None = None, ocio: str = "ocio://default",
                 name: str | None = None, progress: Callable[[str], None] | None = None,
                 renderer: Renderer | None = None) -> dict[str, Any]:
    """Render ``scene_path`` into ``out_dir`` (one EXR + PNG per frame) and write
    ``render.json``: per frame, each task's seconds, what was cached or skipped, and the
    error measures. A ``renderer`` passed in is used (and left open) so that its caches
    serve later renders of the same stage."""
    start = time.perf_counter()
    scene_path = Path(scene_path)
    check_colorspace("lin_ap1_scene", ocio)
    name = name or scene_path.stem
    own = renderer is None
    if renderer is None:
        renderer = Renderer(open_stage_guarded(scene_path), options, progress)
    renderer.options = options
    if options.device:
        set_device(options.device)
    ledger = LEDGER.copy()
    out_dir.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"scene": str(scene_path), "options": _options_json(options),
                           "ocio": ocio, "frames": []}
    try:
        times = [None] if frames is None else list(range(frames[0], frames[1] + 1))
        for t in times:
            t0 = time.perf_counter()
            if progress and t is not None:
                progress(f"frame {t}")
            renderer.last_frame = own and t == times[-1]
            images, log = renderer.render(t)
            frame_name = name if t is None else f"{name}.{t:04d}"
            uv_outputs = write_texture_outputs(out_dir, frame_name, renderer,
                                               renderer.delegate.working_colorspace)
            if own and t == times[-1]:
                renderer.clear_cache()  # no frame follows: its textures go before the writes
            working = renderer.delegate.working_colorspace
            outputs = write_outputs(out_dir, frame_name, images, working, ocio,
                                    options.half_float)
            if uv_outputs:
                outputs["texture_space"] = uv_outputs
            doc["frames"].append({"frame": t, "seconds": time.perf_counter() - t0,
                                  "tasks": log.seconds, "cached": log.cached,
                                  "skipped": log.skipped, "measures": log.measures,
                                  "outputs": outputs})
    finally:
        if own:
            renderer.close()
    doc["total_seconds"] = time.perf_counter() - start
    doc["opencl"] = opencl_summary(ledger)
    atomic_write_json(out_dir / "render.json", doc)
    return doc


def opencl_summary(before: KernelLedger) -> dict[str, Any]:
    """The device, why the others were not used, the programs built and their seconds,
    the kernels launched since ``before``, and the direct/recursive blur switch used."""
    doc = {**device_choice().summary(), **LEDGER.since(before)}
    used = direct_limits()
    if used is not None:  # only if a blur asked for it
        doc["blur_switch"] = asdict(used)
    return doc


def _options_json(options: RenderOptions) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(options).items()}
