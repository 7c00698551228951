"""Texture-space maps by UV rasterisation (vectorised numpy).

For every texel whose centre falls inside a triangle of the UV layout: the surface
position, the interpolated normal, the region weights, a coverage flag, and the
stretch, i.e. how many mm of surface one texel spans along u and along v (d'Eon et al.
2007's stretch map, inverted): the diffusion blur uses it to be right in mm whatever
the UV layout. Row j of a map holds v = (j + 0.5) / size; column i holds u.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

CHUNK_CANDIDATES = 4_000_000


@dataclass(frozen=True)
class TextureMaps:
    """Maps of one UV layout at ``size`` x ``size`` texels."""

    size: int
    triangle: NDArray[np.int32]  # (H, W), -1 where no triangle
    position: NDArray[np.float32]  # (H, W, 3) scene units
    normal: NDArray[np.float32]  # (H, W, 3) unit length where covered
    mm_per_texel_u: NDArray[np.float32]  # (H, W)
    mm_per_texel_v: NDArray[np.float32]  # (H, W)
    region_weights: NDArray[np.float32] | None  # (H, W, R)

    @property
    def coverage(self) -> NDArray[np.float32]:
        return (self.triangle >= 0).astype(np.float32)


def vertex_normals(points: NDArray[np.float64], tris: NDArray[np.int32]) -> NDArray[np.float64]:
    """Area-weighted vertex normals (zero-area neighbourhoods get +z)."""
    p = points[tris]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 x area
    n = np.zeros_like(points)
    for k in range(3):
        np.add.at(n, tris[:, k], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])


def rasterize(
    points: NDArray[np.float64], tris: NDArray[np.int32], uv: NDArray[np.float64],
    uv_tris: NDArray[np.int32], size: int, meters_per_unit: float,
    region_weights: NDArray[np.float64] | None = None,
) -> TextureMaps:
    """Rasterise triangles (vertex indices ``tris``, UV indices ``uv_tris``) at ``size``."""
    if not 8 <= size <= 16384:
        raise InputError(f"texture size must be 8-16384 texels, got {size}")
    if not np.all(np.isfinite(uv)):
        raise InputError("non-finite texture coordinates")
    q = uv * size - 0.5  # texel centres at integer coordinates
    tq = q[uv_tris]  # (T, 3, 2)
    tp = points[tris]  # (T, 3, 3)
    e1, e2 = tq[:, 1] - tq[:, 0], tq[:, 2] - tq[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    # stretch: world distance per texel step along u and v (J = dP/d(texel))
    inv = np.zeros((tris.shape[0], 2, 2))
    inv[ok, 0, 0], inv[ok, 0, 1] = e2[ok, 1] / det[ok], -e2[ok, 0] / det[ok]
    inv[ok, 1, 0], inv[ok, 1, 1] = -e1[ok, 1] / det[ok], e1[ok, 0] / det[ok]
    edges = np.stack([tp[:, 1] - tp[:, 0], tp[:, 2] - tp[:, 0]], axis=2)  # (T, 3, 2)
    jac = edges @ inv  # (T, 3, 2): columns d P / d u_texel, d P / d v_texel
    mm = meters_per_unit * 1000.0
    tri_mm_u = np.linalg.norm(jac[:, :, 0], axis=1) * mm
    tri_mm_v = np.linalg.norm(jac[:, :, 1], axis=1) * mm
    normals = vertex_normals(points, tris)

    triangle = np.full((size, size), -1, np.int32)
    bary = np.zeros((size, size, 2), np.float32)  # b1, b2 (b0 = 1 - b1 - b2)
    lo = np.ceil(tq.min(axis=1)).astype(np.int64).clip(0, size - 1)
    hi = np.floor(tq.max(axis=1)).astype(np.int64).clip(0, size - 1)
    wdt = np.where(ok, hi[:, 0] - lo[:, 0] + 1, 0).clip(0)
    hgt = np.where(ok, hi[:, 1] - lo[:, 1] + 1, 0).clip(0)
    counts = wdt * hgt
    ids = np.flatnonzero(counts > 0)
    csum = np.cumsum(counts[ids])
    start = 0
    while start < ids.size:
        end = int(np.searchsorted(csum, (csum[start - 1] if start else 0) + CHUNK_CANDIDATES,
                                  side="right"))
        end = max(end, start + 1)
        chunk = ids[start:end]
        n = counts[chunk]
        t = np.repeat(chunk, n)
        k = np.arange(int(n.sum())) - np.repeat(np.cumsum(n) - n, n)
        row, col = np.divmod(k, wdt[t])
        x, y = lo[t, 0] + col, lo[t, 1] + row
        dx, dy = x - tq[t, 0, 0], y - tq[t, 0, 1]
        inv_det = 1.0 / det[t]
        b1 = (dx * e2[t, 1] - dy * e2[t, 0]) * inv_det
        b2 = (e1[t, 0] * dy - e1[t, 1] * dx) * inv_det
        inside = np.flatnonzero((b1 >= -1e-9) & (b2 >= -1e-9) & (b1 + b2 <= 1 + 1e-9))
        yi, xi = y[inside], x[inside]
        triangle[yi, xi] = t[inside]
        bary[yi, xi, 0] = b1[inside]
        bary[yi, xi, 1] = b2[inside]
        start = end
    covered = triangle >= 0
    tri_c = triangle[covered]
    corner = tris[tri_c]  # (N, 3) vertex indices
    b12 = bary[covered]
    w0 = 1 - b12[:, 0] - b12[:, 1]
    # every per-vertex attribute in one (V, 6 + R) table: three gathers of whole rows
    table = np.concatenate([np.asarray(points, np.float32), normals.astype(np.float32)]
                           + ([np.asarray(region_weights, np.float32)]
                              if region_weights is not None else []), axis=1)
    attrs = table[corner[:, 0]] * w0[:, None]
    attrs += table[corner[:, 1]] * b12[:, :1]
    attrs += table[corner[:, 2]] * b12[:, 1:]
    position = np.zeros((size, size, 3), np.float32)
    position[covered] = attrs[:, :3]
    normal = np.zeros((size, size, 3), np.float32)
    nrm = attrs[:, 3:6]
    normal[covered] = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    mm_u = np.zeros((size, size), np.float32)
    mm_v = np.zeros((size, size), np.float32)
    mm_u[covered], mm_v[covered] = tri_mm_u[tri_c], tri_mm_v[tri_c]
    regions = None
    if region_weights is not None:
        regions = np.zeros((size, size, region_weights.shape[1]), np.float32)
        regions[covered] = attrs[:, 6:]
    return TextureMaps(size, triangle, position, normal, mm_u, mm_v, regions)
