"""Interleaved shadow sampling (Keller & Heidrich 2001): texel classes that each trace
a share of a light's samples, the period chosen from the texels an image pixel holds,
and the visibility each texel gets from its neighbours' classes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..device.choice import Device
from ..scene import Camera
from ..surface.texture_maps import (
    TextureMaps,
)
from .irradiance import (
    IrradianceResult,
    filter_interleaved,
    visibility_plane,
    visibility_planes,
)

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
                           normal: NDArray[np.float32] | None = None,
                           device: Device | None = None) -> dict[str, NDArray[np.float32]]:
    """Each light's per-texel visibility from interleaved shadow rays of ``period``,
    reconstructed in texture space (``filter_interleaved``) and returned per covered
    texel (``texel``: the points' flat indices, in their order; by default row order).
    ``normal``: the maps' normal map where they let it go (:func:`normal_map`);
    ``device``: as :func:`filter_interleaved`'s."""
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
                                  at=texel, period=period, device=device)
    return {**res.visibility, **dict(zip(paths, filtered, strict=True))}
