"""Texture-space maps by UV rasterisation (OpenCL; a vectorised numpy reference).

For every texel whose centre falls inside a triangle of the UV layout: the surface
position, the interpolated normal, the region weights, a coverage flag, and the
stretch, i.e. how many mm of surface one texel spans along u and along v (d'Eon et al.
2007's stretch map, inverted): the diffusion blur uses it to be right in mm whatever
the UV layout. Row j of a map holds v = (j + 0.5) / size; column i holds u.

:func:`rasterize` runs on the OpenCL device (one work item per triangle claims the
texels whose centres it covers, the highest triangle index winning a shared edge as
the numpy version's last write does; one per texel interpolates the attributes);
:func:`rasterize_reference` is the numpy version it is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device, or_default
from ..device.memory import host_buffer, host_output, read_output
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from .resample import take_rows

CHUNK_CANDIDATES = 4_000_000

REGION_WEIGHT_DTYPE = np.float16
"""The texels' region weights are kept as half floats: 0 and 1 (a texel inside one
region) exactly, blends within 2.4e-4. Float32 held 403 MB of the render's peak at
texture 4096 with six regions, and on the benchmark host new memory costs about 2 s of
CPU a GB in the kernel on first touch (docs/benchmarks.md)."""

@dataclass(frozen=True)
class TexelRegions:
    """What each texel's region weights are made from: the triangle map, each triangle's
    ``frame`` ((T, 8) float32: its first corner in texels, its two edges from there, 1
    over their determinant, 0), its vertices (``corners`` (T, 3) int32) and each vertex's
    weights (``weights`` (V, R) float32). The diffusion makes the weights per texel from
    them in float32 (the texel centre's barycentrics, the corners' weights interpolated),
    rather than read the maps' (201 MB at texture 4096 with six regions), which hold the
    same within their half floats' rounding."""

    triangle: NDArray[np.int32]
    frame: NDArray[np.float32]
    corners: NDArray[np.int32]
    weights: NDArray[np.float32]


def at_texels(triangle: NDArray[np.int32], per_triangle: NDArray[Any], off: Any
              ) -> NDArray[Any]:
    """A per-triangle value (T,) at each texel of ``triangle`` (a triangle map or a box of
    one; -1 where no triangle), ``off`` where none covers it, in ``per_triangle``'s
    dtype."""
    return texels_from_table(triangle, off_first(per_triangle, off))


def off_first(per_triangle: NDArray[Any], off: Any) -> NDArray[Any]:
    """(T + 1,) ``off`` then the per-triangle values: :func:`texels_from_table`'s table."""
    table = np.empty(per_triangle.shape[0] + 1, per_triangle.dtype)
    table[0] = off
    table[1:] = per_triangle
    return table


def texels_from_table(triangle: NDArray[np.int32], table: NDArray[Any]) -> NDArray[Any]:
    """:func:`at_texels` through its table (:func:`off_first`): one gather at the
    triangle index plus one (a where, a maximum and a fancy index took 2.5-3 times as
    long: the seam layout reads 14.5 M texels of each stretch map per level at texture
    4096)."""
    return np.take(table, np.add(triangle, 1, dtype=np.intp))


@dataclass(frozen=True)
class TriangleStretch:
    """One axis's stretch map made from the triangles where it is read: ``[box]`` (rows
    and columns, as of the (H, W) map) gives the map's float32 values there, each
    texel's triangle's own mm per texel (0 off the charts), which is what the maps hold.
    The seam layout reads its charts' boxes of it rather than hold two texture-sized
    maps (0.13 GB at texture 4096)."""

    triangle: NDArray[np.int32]
    mm: NDArray[np.float32]
    """(T + 1,) 0, then each triangle's mm per texel along this axis
    (:func:`off_first`)."""

    def __getitem__(self, box: Any) -> NDArray[np.float32]:
        return texels_from_table(self.triangle[box], self.mm)


@dataclass(frozen=True)
class TexelSurface:
    """What each texel's position and normal are made from: the triangle map, each
    triangle's UV corners in texel coordinates (``corners_texels`` (T, 3, 2) float64)
    and the determinant of its UV edges, its vertices (``corners`` (T, 3) int32) and each
    vertex's position and normal (``table`` (V, 6) float32). :meth:`at` makes them at
    the texels asked for with :func:`rasterize`'s arithmetic, the maps' own floats: the
    seam layout reads them at its margins' start texels (a few hundred thousand at
    texture 4096) without holding the maps (0.4 GB)."""

    triangle: NDArray[np.int32]
    corners_texels: NDArray[np.float64]
    det: NDArray[np.float64]
    corners: NDArray[np.int32]
    table: NDArray[np.float32]

    def at(self, texels: NDArray[np.int64]
           ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """(N, 3) position (scene units) and unit normal at flat texel indices (N,), zero
        where no triangle covers the texel, as in the maps: ``texel_attributes``'
        operations in its order (float64 barycentrics rounded to float32, float32 sums
        without fused multiply-adds)."""
        w = self.triangle.shape[1]
        t = self.triangle.reshape(-1)[texels]
        position = np.zeros((t.size, 3), np.float32)
        normal = np.zeros((t.size, 3), np.float32)
        on = np.flatnonzero(t >= 0)
        t, texels = t[on], texels[on]
        q = self.corners_texels[t]
        ax, ay = q[:, 0, 0], q[:, 0, 1]
        e1x, e1y = q[:, 1, 0] - ax, q[:, 1, 1] - ay
        e2x, e2y = q[:, 2, 0] - ax, q[:, 2, 1] - ay
        inv = 1.0 / self.det[t]  # a triangle that covers a texel is not degenerate
        dx, dy = (texels % w).astype(np.float64) - ax, (texels // w).astype(np.float64) - ay
        b1 = ((dx * e2y - dy * e2x) * inv).astype(np.float32)[:, None]
        b2 = ((e1x * dy - e1y * dx) * inv).astype(np.float32)[:, None]
        w0 = np.float32(1.0) - b1 - b2
        v = self.corners[t]
        attrs = self.table[v[:, 0]] * w0 + self.table[v[:, 1]] * b1 + self.table[v[:, 2]] * b2
        n = attrs[:, 3:6]
        length = np.sqrt(n[:, 0] * n[:, 0] + n[:, 1] * n[:, 1] + n[:, 2] * n[:, 2])
        position[on] = attrs[:, :3]
        normal[on] = n * (np.float32(1.0) / np.maximum(length, np.float32(1e-12)))[:, None]
        return position, normal


@dataclass(frozen=True)
class TextureMaps:
    """Maps of one UV layout at ``size`` x ``size`` texels."""

    size: int
    triangle: NDArray[np.int32]  # (H, W), -1 where no triangle
    position: NDArray[np.float32] | None  # (H, W, 3) scene units; None once let go
    normal: NDArray[np.float32] | None  # (H, W, 3) unit length where covered; likewise
    mm_per_texel_u: NDArray[np.float32]  # (H, W); see without_surface
    mm_per_texel_v: NDArray[np.float32]  # (H, W)
    region_weights: NDArray[np.float16] | None  # (H, W, R), see REGION_WEIGHT_DTYPE
    texel_surface: TexelSurface
    """What the position and normal are made from, texel by texel (kept once they go)."""
    tri_mm: NDArray[np.float32] | None = None
    """(T, 2): each triangle's mm per texel along u and v, which the stretch maps hold at
    its texels (:meth:`texel_area_mm2` once the maps let them go)."""
    texel_regions: TexelRegions | None = None
    """What the region weights are made from (None: no regions, or the maps' own only)."""

    @property
    def surface(self) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """The (position, normal) maps; an error once :meth:`without_surface` let them
        go."""
        if self.position is None or self.normal is None:
            raise RuntimeError("these texture maps' position and normal maps were let go "
                               "(TextureMaps.without_surface)")
        return self.position, self.normal

    def without_surface(self, keep_stretch: bool = True, keep_regions: bool = True
                        ) -> TextureMaps:
        """These maps less the position and normal maps, which only the irradiance and
        the seam layout read (0.4 GB at texture 4096); unless ``keep_stretch`` the
        stretch maps, which the layout and the blur schedule read (0.13 GB; the texel
        areas are then made from the triangles' own, :meth:`texel_area_mm2`); unless
        ``keep_regions`` the region weights, which a layout made with
        :attr:`texel_regions` makes again per texel (0.2 GB): for a render's last frame
        once those are made. The coverage array stays the same one (made now if it was
        not: each copy would make its own)."""
        if not keep_stretch and self.tri_mm is None:
            raise ValueError("these texture maps have no per-triangle stretch to keep "
                             "their texel areas by")
        out = replace(self, position=None, normal=None)
        if not keep_stretch:
            out = replace(out, mm_per_texel_u=None, mm_per_texel_v=None)
        if not keep_regions:
            out = replace(out, region_weights=None)
        out.__dict__["coverage"] = self.coverage  # cached_property's value, not a field
        return out

    def texel_area_mm2(self, rows: slice = slice(None)) -> NDArray[np.float32]:
        """(rows, W) each texel's area in mm^2, mm per texel along u times along v (0 off
        the charts), from the stretch maps or, once they are let go, from the
        triangles' (the same float32 products)."""
        if self.mm_per_texel_u is not None and self.mm_per_texel_v is not None:
            return self.mm_per_texel_u[rows] * self.mm_per_texel_v[rows]
        u, v = self.triangle_stretch()  # without_surface keeps one or the other
        return u[rows] * v[rows]

    def triangle_stretch(self) -> tuple[TriangleStretch, TriangleStretch]:
        """The stretch maps along u and v as made from the triangles where read (the
        same float32 values as the maps')."""
        if self.tri_mm is None:
            raise ValueError("these texture maps have no per-triangle stretch")
        return self._stretch_tables

    @cached_property
    def _stretch_tables(self) -> tuple[TriangleStretch, TriangleStretch]:
        """:meth:`triangle_stretch`'s tables, made once (the flux reads them band by
        band)."""
        assert self.tri_mm is not None
        return (TriangleStretch(self.triangle, off_first(self.tri_mm[:, 0], 0.0)),
                TriangleStretch(self.triangle, off_first(self.tri_mm[:, 1], 0.0)))

    @cached_property
    def coverage(self) -> NDArray[np.float32]:
        """(H, W) 1 where a triangle covers the texel, else 0: one read-only array that
        every task shares (one each held 67 MB apiece at texture 4096)."""
        cov = (self.triangle >= 0).astype(np.float32)
        cov.setflags(write=False)
        return cov


def texel_rows(texture: NDArray[Any], texels: NDArray[np.intp]) -> NDArray[Any]:
    """The rows (N, C) of an (H, W, C) ``texture`` at flat texel indices (N,)
    (:func:`~.resample.take_rows`: 3-5x faster than a boolean mask over (H, W, C) maps)."""
    return take_rows(texture.reshape(-1, texture.shape[-1]), texels)


TEXEL_BLOCK = 32
"""Side in texels of the square blocks :func:`texels_in_blocks` orders texels by."""


def texels_in_blocks(covered: NDArray[np.bool_], block: int = TEXEL_BLOCK
                     ) -> NDArray[np.int64]:
    """The flat indices of the True texels of ``covered`` (H, W), block by block: square
    blocks of ``block`` texels in row order, row order within each. Texels next to each
    other on the surface stay next to each other, as a Morton order of their positions
    keeps them, without a sort: the demo face's shadow rays at texture 1024 and 4096
    took as long in this order as in a Morton order, which took 0.05 and 0.9 s to
    make (this: 0.01 and 0.2 s)."""
    h, w = covered.shape
    hb, wb = -(-h // block), -(-w // block)
    padded = np.zeros((hb * block, wb * block), bool)
    padded[:h, :w] = covered
    columns = np.arange(wb * block, dtype=np.int64)
    rows = []
    for y0 in range(0, hb * block, block):  # a row of blocks at a time: no H x W index
        flat = np.arange(y0, y0 + block, dtype=np.int64)[:, None] * w + columns
        mine = padded[y0:y0 + block].reshape(block, wb, block).transpose(1, 0, 2)
        rows.append(flat.reshape(block, wb, block).transpose(1, 0, 2)[mine])
    return np.concatenate(rows)


def vertex_normals(points: NDArray[np.float64], tris: NDArray[np.int32]) -> NDArray[np.float64]:
    """Area-weighted vertex normals (zero-area neighbourhoods get +z)."""
    p = points[tris]
    face_n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # length = 2 x area
    n = np.zeros_like(points)
    for k in range(3):
        np.add.at(n, tris[:, k], face_n)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.where(length > 0, n / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])


def triangle_jacobians(points: NDArray[np.float64], tris: NDArray[np.int32],
                       uv: NDArray[np.float64], uv_tris: NDArray[np.int32], size: int
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per triangle its UV corners in texel coordinates (T, 3, 2; texel centres at
    integers: x = u size - 0.5, y = v size - 0.5), the determinant of its UV edges, and
    J = dP / d texel (T, 3, 2; scene units per texel step along x and y; zero where the
    UV triangle is degenerate)."""
    q = uv * size - 0.5  # texel centres at integer coordinates
    tq = q[uv_tris]  # (T, 3, 2)
    tp = points[tris]  # (T, 3, 3)
    e1, e2 = tq[:, 1] - tq[:, 0], tq[:, 2] - tq[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    ok = np.abs(det) > 1e-12
    inv = np.zeros((tris.shape[0], 2, 2))
    inv[ok, 0, 0], inv[ok, 0, 1] = e2[ok, 1] / det[ok], -e2[ok, 0] / det[ok]
    inv[ok, 1, 0], inv[ok, 1, 1] = -e1[ok, 1] / det[ok], e1[ok, 0] / det[ok]
    edges = np.stack([tp[:, 1] - tp[:, 0], tp[:, 2] - tp[:, 0]], axis=2)  # (T, 3, 2)
    return tq, det, edges @ inv


def texels_per_scene_unit(jacobian: NDArray[np.float64]) -> NDArray[np.float64]:
    """(T, 2, 3) per triangle J^+ = (J^T J)^-1 J^T of :func:`triangle_jacobians`' J
    (T, 3, 2): texels per scene unit along the surface, a vector in the triangle's
    plane mapped to texels (zero where J is; closed form: numpy's batched SVD took 24 s
    on the demo)."""
    j = jacobian
    jtj = np.einsum("tki,tkj->tij", j, j)
    det = jtj[:, 0, 0] * jtj[:, 1, 1] - jtj[:, 0, 1] * jtj[:, 1, 0]
    inv = np.stack([np.stack([jtj[:, 1, 1], -jtj[:, 0, 1]], axis=1),
                    np.stack([-jtj[:, 1, 0], jtj[:, 0, 0]], axis=1)], axis=1)
    inv /= np.where(np.abs(det) > 1e-300, det, np.inf)[:, None, None]
    return np.einsum("tij,tkj->tik", inv, j)


def _triangles(points: NDArray[np.float64], tris: NDArray[np.int32], uv: NDArray[np.float64],
               uv_tris: NDArray[np.int32], size: int, meters_per_unit: float
               ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
                          NDArray[np.float64], NDArray[np.float64]]:
    """Checked input; per triangle its UV corners in texel coordinates (T, 3, 2), the
    determinant of its UV edges, and mm of surface per texel step along u and v (the
    stretch, J = dP / d texel); the vertex normals."""
    if not 8 <= size <= 16384:
        raise InputError(f"texture size must be 8-16384 texels, got {size}")
    if not np.all(np.isfinite(uv)):
        raise InputError("non-finite texture coordinates")
    tq, det, jac = triangle_jacobians(points, tris, uv, uv_tris, size)
    mm = meters_per_unit * 1000.0
    tri_mm_u = np.linalg.norm(jac[:, :, 0], axis=1) * mm
    tri_mm_v = np.linalg.norm(jac[:, :, 1], axis=1) * mm
    return tq, det, tri_mm_u, tri_mm_v, vertex_normals(points, tris)


def _attribute_table(points: NDArray[np.float64], normals: NDArray[np.float64],
                     region_weights: NDArray[np.float64] | None) -> NDArray[np.float32]:
    """Every per-vertex attribute in one (V, 6 + R) table: position, normal, regions."""
    return np.concatenate([np.asarray(points, np.float32), normals.astype(np.float32)]
                          + ([np.asarray(region_weights, np.float32)]
                             if region_weights is not None else []), axis=1)


def rasterize_reference(
    points: NDArray[np.float64], tris: NDArray[np.int32], uv: NDArray[np.float64],
    uv_tris: NDArray[np.int32], size: int, meters_per_unit: float,
    region_weights: NDArray[np.float64] | None = None,
) -> TextureMaps:
    """:func:`rasterize` in vectorised numpy (one thread): the reference for its tests."""
    tq, det, tri_mm_u, tri_mm_v, normals = _triangles(points, tris, uv, uv_tris, size,
                                                      meters_per_unit)
    e1, e2 = tq[:, 1] - tq[:, 0], tq[:, 2] - tq[:, 0]
    ok = np.abs(det) > 1e-12
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
    table = _attribute_table(points, normals, region_weights)  # three gathers of rows
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
        regions = np.zeros((size, size, region_weights.shape[1]), REGION_WEIGHT_DTYPE)
        regions[covered] = np.maximum(attrs[:, 6:], np.float32(0.0))
    return TextureMaps(size, triangle, position, normal, mm_u, mm_v, regions,
                       _texel_surface(triangle, tq, det, tris, table),
                       np.stack([tri_mm_u, tri_mm_v], 1).astype(np.float32),
                       _texel_regions(triangle, tq, det, tris, region_weights))


_KERNEL = cl_source(__package__, "texture_maps.cl")


@lru_cache(maxsize=4)
def texture_kernels(device: Device) -> tuple[Any, Any]:
    program = build(device, _KERNEL)
    return Kernel(program, "claim_texels", 1), Kernel(program, "texel_attributes", 2)


def rasterize(
    points: NDArray[np.float64], tris: NDArray[np.int32], uv: NDArray[np.float64],
    uv_tris: NDArray[np.int32], size: int, meters_per_unit: float,
    region_weights: NDArray[np.float64] | None = None, device: Device | None = None,
) -> TextureMaps:
    """Rasterise triangles (vertex indices ``tris``, UV indices ``uv_tris``) at ``size``
    on the OpenCL device: the maps of :func:`rasterize_reference` (the same float64
    coverage test and float32 interpolation; normals within float32 rounding).
    ``device``: where it runs (None: :func:`~..device.choice.or_default`)."""
    tq, det, tri_mm_u, tri_mm_v, normals = _triangles(points, tris, uv, uv_tris, size,
                                                      meters_per_unit)
    device = or_default(device)
    queue = device.queue
    claim, attributes = texture_kernels(device)
    n_tris = tq.shape[0]
    n_regions = 0 if region_weights is None else int(np.shape(region_weights)[1])

    # over the host arrays: each is kept (named) until the queue is done with it
    tq, det, tris = (np.ascontiguousarray(a, t) for a, t in ((tq, np.float64),
                                                          (det, np.float64),
                                                          (tris, np.int32)))
    tq_buf, det_buf = host_buffer(device, tq), host_buffer(device, det)
    corner_buf = host_buffer(device, tris)
    table = _attribute_table(points, normals, region_weights)
    table_buf = host_buffer(device, table)
    tri_mm = np.stack([tri_mm_u, tri_mm_v], 1).astype(np.float32)
    tri_mm_buf = host_buffer(device, tri_mm)
    triangle = np.full((size, size), -1, np.int32)
    tri_buf = host_output(device, triangle)
    if n_tris:
        claim(queue, (n_tris,), None, tq_buf, det_buf, tri_buf, np.int32(size),
              np.int32(n_tris))
    out = {"position": np.empty((size, size, 3), np.float32),
           "normal": np.empty((size, size, 3), np.float32),
           "mm_u": np.empty((size, size), np.float32), "mm_v": np.empty((size, size), np.float32),
           "regions": np.empty((size, size, n_regions) if n_regions else 1,
                               REGION_WEIGHT_DTYPE)}
    bufs = {k: host_output(device, v) for k, v in out.items()}
    attributes(queue, (size, size), None, tri_buf, tq_buf, det_buf, corner_buf, table_buf,
               tri_mm_buf, bufs["position"],
               bufs["normal"], bufs["mm_u"], bufs["mm_v"], bufs["regions"], np.int32(size),
               np.int32(n_regions))
    read_output(device, tri_buf, triangle)
    for k, v in out.items():
        read_output(device, bufs[k], v)
    return TextureMaps(size, triangle, out["position"], out["normal"], out["mm_u"],
                       out["mm_v"], out["regions"] if n_regions else None,
                       _texel_surface(triangle, tq, det, tris, table), tri_mm,
                       _texel_regions(triangle, tq, det, tris, region_weights))


def _texel_surface(triangle: NDArray[np.int32], tq: NDArray[np.float64],
                   det: NDArray[np.float64], tris: NDArray[Any], table: NDArray[np.float32]
                   ) -> TexelSurface:
    return TexelSurface(triangle, np.asarray(tq, np.float64).reshape(-1, 3, 2),
                        np.asarray(det, np.float64), np.ascontiguousarray(tris, np.int32),
                        np.ascontiguousarray(table[:, :6]))


def _texel_regions(triangle: NDArray[np.int32], tq: NDArray[np.float64],
                   det: NDArray[np.float64], tris: NDArray[Any],
                   region_weights: NDArray[Any] | None) -> TexelRegions | None:
    if region_weights is None:
        return None
    corners = np.asarray(tq, np.float64).reshape(-1, 3, 2)
    frame = np.zeros((corners.shape[0], 8), np.float32)
    frame[:, 0:2] = corners[:, 0]
    frame[:, 2:4] = corners[:, 1] - corners[:, 0]
    frame[:, 4:6] = corners[:, 2] - corners[:, 0]
    with np.errstate(divide="ignore"):  # a degenerate triangle claims no texel
        frame[:, 6] = 1.0 / np.asarray(det, np.float64)
    return TexelRegions(triangle, frame, np.ascontiguousarray(tris, np.int32),
                        np.ascontiguousarray(region_weights, np.float32))

