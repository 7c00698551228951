"""What a chart tile's margin reads across a UV seam: for each margin texel, the surface
point it stands for, found by casting from the chart's tangent plane onto the mesh
(Embree), and the texel of the neighbouring chart that holds it."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device
from ..device.memory import host_buffer, run_on_host_arrays
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from ..sorting import unique_keys
from ..surface.texture_maps import texels_per_scene_unit


@dataclass(frozen=True)
class SeamGeometry:
    """The surface the margins are read from: the Embree scene with the skin mesh in it
    (``mesh_index``), per triangle its chart, its UV corners in finest texel
    coordinates and J = dP / d texel (scene units), per finest texel its triangle, and
    ``surface_at``, the position and normal (scene units) at finest texels, made from
    the triangles (:meth:`~.texture_maps.TexelSurface.at`: the maps' own floats, without
    holding the maps)."""

    device: Device
    """Where the margin points' arithmetic runs (if it has doubles, else numpy)."""
    rays: Any  # ..raytrace.RayScene
    mesh_index: int
    tri_chart: NDArray[np.int32]
    uv_corners: NDArray[np.float64]
    jacobian: NDArray[np.float64]
    triangle: NDArray[np.int32]
    surface_at: Callable[[NDArray[np.int64]], tuple[NDArray[np.float32], NDArray[np.float32]]]
    """(N, 3) position and normal at flat finest texel indices (N,)."""
    mm_per_unit: float = 1.0
    """mm a scene unit (the stage's metersPerUnit x 1000)."""

    @cached_property
    def texels_per_scene_unit(self) -> NDArray[np.float64]:
        """(T, 2, 3) per triangle J^+: finest texels per scene unit along the surface
        (:func:`~..surface.texture_maps.texels_per_scene_unit`)."""
        return texels_per_scene_unit(self.jacobian)

    @cached_property
    def device_buffers(self) -> dict[str, Any]:
        """The per-triangle arrays the device's ``margin_hits`` reads (every level's):
        the ray scene's owners, each triangle's UV corners, J^+ and chart."""
        d = self.device
        return {"owner": host_buffer(d, self.rays.owner.astype(np.int64)),
                "corners": host_buffer(d, self.uv_corners.astype(np.float64)),
                "inverse_jac": host_buffer(d, self.texels_per_scene_unit),
                "tri_chart": host_buffer(d, self.tri_chart.astype(np.int32))}


def _read_reach(level: int) -> int:
    """Texels either side of a read at ``level`` that its kernel reaches."""
    return 1 if level == 0 else 2


SEAM_SUBSAMPLES = 4
"""Points along each axis of a texel its chart's border crosses that look for the
charts across the border, over what its splat reaches (its square at level 0, two
texels at coarser levels: the other side's splat reaches as far): the texel's centre
lies on its own chart, so the other chart is found where one of these lands, and the
centre carried into it from there. Points over the square alone lost 15-45% of a pencil
at a seam at levels 1-4, points short of the reach's edge 5-23%."""


def _subsamples(level: int) -> NDArray[np.float64]:
    """(S, 2) offsets (texels) over a partly covered texel's reach at ``level``."""
    # to the reach's very edge: a texel 0.9 of a texel inside its chart still takes a
    # tenth of the other side's neighbour
    t = np.linspace(-1.0, 1.0, SEAM_SUBSAMPLES) * (1.0 if level > 0 else 0.5)
    ox, oy = np.meshgrid(t, t)
    return np.stack([ox.ravel(), oy.ravel()], axis=1)


def _margin_sources(g: SeamGeometry, level: int, shift: NDArray[np.int64],
                    count: NDArray[np.float32], margin: NDArray[np.bool_],
                    full: NDArray[np.bool_], nearest: NDArray[np.int32],
                    owner: NDArray[np.int32], w: int
                    ) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Where the texels in ``margin`` read the surface across a seam (module docstring):
    the texel each read is for and the read's atlas position in the other chart's tile.

    A point: the chart's tangent plane at the texel's nearest fully covered texel b,
    extrapolated to it, projected onto the skin mesh along b's normal; the hit's texture
    coordinates. A texel no chart covers reads at its centre (any chart, its own too:
    a chart may meet itself at a seam). A texel its own chart covers in part looks at
    :func:`_subsamples` points over its square; per other chart hit (or its own, hit
    more than two texels from where the point lies in the tile) it reads once, at its
    centre carried into that chart, P_hit - J_hit^+ J_b o (o the point's offset from
    the centre). Points that miss the skin (beyond the scan's edge), or land farther
    from the tangent plane than half the way out plus two texels, are dropped."""
    sub = _subsamples(level)
    # int32 (the atlas holds fewer than 2^31 texels), each chunk int64 as it is read:
    # the level's margin texels are held through its reads (3.8 M at level 0 of
    # texture 4096)
    texels = np.flatnonzero(margin).astype(np.int32)
    # in chunks of texels (a texel's points stay together): the points' float64
    # intermediates took 1.8 GiB beside the layout at texture 2048 in one piece
    points = np.cumsum(np.where(count[texels] <= 1e-6, np.int8(1), np.int8(sub.shape[0])),
                       dtype=np.int64)
    per_chunk = MARGIN_POINTS_IN_FLIGHT // MARGIN_THREADS
    bounds = np.searchsorted(points, np.arange(per_chunk, int(points[-1]) if points.size
                                               else 0, per_chunk))
    del points
    key_of = int(g.tri_chart.max(initial=0)) + 1

    def reads(chunk: NDArray[np.int32]) -> list[tuple[Any, Any, Any]]:
        return _margin_reads(g, level, shift, count, full, nearest, owner, w,
                             chunk.astype(np.int64), sub, key_of)

    # numpy and Embree release the GIL for most of a chunk's work: chunks side by side
    with ThreadPoolExecutor(MARGIN_THREADS) as pool:
        pieces = [p for chunk in pool.map(reads, np.split(texels, bounds)) for p in chunk]
    if not pieces:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.float32)
    # each column's pieces go once joined, not through the means (0.2 GB of the level-0
    # reads at texture 4096, at the layout's peak)
    columns = [list(column) for column in zip(*pieces, strict=True)]
    del pieces
    m, xy, chart = (np.concatenate(columns.pop(0)) for _ in range(3))
    del columns
    m_out, xy_out, _ = _mean_per_key(m, chart, xy, key_of)
    return m_out, xy_out.astype(np.float32)


MARGIN_THREADS = min(os.cpu_count() or 1, 4)
"""Chunks of :func:`_margin_reads` run side by side (numpy and Embree release the GIL for
most of the work)."""
MARGIN_POINTS_IN_FLIGHT = 1 << 20
"""Points all of :func:`_margin_reads`' threads handle at once (about 400 MB of
intermediates), split evenly between them."""


def _margin_reads(g: SeamGeometry, level: int, shift: NDArray[np.int64],
                  count: NDArray[np.float32], full: NDArray[np.bool_],
                  nearest: NDArray[np.int32], owner: NDArray[np.int32], w: int,
                  m_all: NDArray[np.int64], sub: NDArray[np.float64], key_of: int
                  ) -> list[tuple[NDArray[np.int64], NDArray[np.float64], NDArray[Any]]]:
    """The reads of :func:`_margin_sources` for the margin texels ``m_all``: (texels,
    atlas positions, source charts) pieces, one read per texel and chart landed on,
    then the fully covered texels a partly covered one's read reaches. Each point's
    arithmetic on the device where it has doubles (:func:`_device_points`), else in
    numpy (:func:`_numpy_points`): the same operations in the same order, so the same
    reads bit for bit."""
    if m_all.size == 0:
        return []
    empty = count[m_all] <= 1e-6
    # the points: one per texel no chart covers, then SEAM_SUBSAMPLES^2 per partly
    # covered texel (its offsets ``sub``), each from its texel's start texel b
    starts_of = nearest[m_all]
    first_of, b_texel, _ = unique_keys(starts_of)  # np.unique's, by a packed sort
    start = starts_of[first_of]
    texels = _PointTexels(m_all[empty], m_all[~empty], sub,
                          np.concatenate([b_texel[empty], b_texel[~empty]]).astype(np.int32))
    position, normal, jac_b = _cell_frames(g, level, shift, owner, start, w)
    frames = (start, position, normal, jac_b, _norm_axis1(jac_b).max(axis=1))
    points = _device_points if g.device.has_doubles else _numpy_points
    kept, chart, level_xy, t_local = points(g, level, shift, owner, w, texels, frames)
    m_read, xy_read, first = _mean_per_key(texels.texel_of(kept), chart, level_xy, key_of)
    read = kept[first]
    # the fully covered texels up to a read's reach from a partly covered one read that
    # chart too, at their centres carried along the chart's parameterization: the other
    # side's splat reaches a texel past its border, and a read as far again (without
    # them a pencil at a seam lost 5-19% at levels 1 and 4)
    src = np.flatnonzero(read >= texels.n_empty)
    carry = np.einsum("mij,mjk->mik", np.take(g.texels_per_scene_unit, t_local[first[src]],
                                              axis=0),
                      np.take(jac_b, texels.b_of(read[src]), axis=0)) / (1 << level)
    m_src, chart_src = m_read[src], chart[first[src]]
    xy_src = np.take(xy_read, src, axis=0)
    pieces = [(m_read, xy_read, chart[first])]
    ring = range(-_read_reach(level), _read_reach(level) + 1)
    n = count.size
    for dy in ring:
        for dx in ring:
            m2 = np.clip(m_src + dy * w + dx, 0, n - 1)
            keep = np.flatnonzero(full[m2] & (owner[m2] == owner[m_src]))
            pieces.append((m2[keep], np.take(xy_src, keep, axis=0)
                           + np.take(carry, keep, axis=0) @ np.array([dx, dy], float),
                           chart_src[keep]))
    return pieces


class _PointTexels:
    """The margin points of a chunk: point i < ``n_empty`` is texel ``empty[i]`` at its
    centre; point n_empty + j is texel ``partial[j // S]`` at offset ``sub[j % S]``."""

    def __init__(self, empty: NDArray[np.int64], partial: NDArray[np.int64],
                 sub: NDArray[np.float64], b: NDArray[np.int32]) -> None:
        self.empty, self.partial, self.sub = empty, partial, sub
        self.b = b
        """Per texel (empty ones, then partial ones) its start texel's index."""
        self.n_empty = empty.size
        self.count = empty.size + partial.size * sub.shape[0]

    def _texel_index(self, points: NDArray[np.int64]) -> NDArray[np.int64]:
        """Per point its texel's index among the empty, then partial texels."""
        return np.where(points < self.n_empty, points,
                        self.n_empty + (points - self.n_empty) // self.sub.shape[0])

    def texel_of(self, points: NDArray[np.int64]) -> NDArray[np.int64]:
        return np.take(np.concatenate([self.empty, self.partial]), self._texel_index(points))

    def b_of(self, points: NDArray[np.int64]) -> NDArray[np.int32]:
        return np.take(self.b, self._texel_index(points))

    def offsets(self) -> NDArray[np.float64]:
        """(points, 2): every point's offset from its texel's centre."""
        return np.concatenate([np.zeros((self.n_empty, 2)),
                               np.tile(self.sub, (self.partial.size, 1))])


def _numpy_points(g: SeamGeometry, level: int, shift: NDArray[np.int64],
                  owner: NDArray[np.int32], w: int, texels: _PointTexels,
                  frames: tuple[NDArray[Any], ...]
                  ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float64],
                             NDArray[np.int64]]:
    """Each margin point carried across the seam (:func:`_margin_sources`): the points
    whose read counts (ascending), and per such point the chart it reads, its atlas
    position there and the skin triangle it landed on. The reference of the device's
    ``margin_rays`` and ``margin_hits``."""
    scale = 1 << level
    start, position, normal, jac_b, jac_norm = frames
    point = np.arange(texels.count)
    m_idx = texels.texel_of(point)
    offset_px = texels.offsets()
    partial = point >= texels.n_empty
    b = texels.b_of(point)
    # rows gathered by np.take throughout (3-10x faster than fancy indexing of rows)
    jac = np.take(jac_b, b, axis=0)  # scene units per level texel
    normal = np.take(normal, b, axis=0)
    here = np.stack([m_idx % w, m_idx // w], axis=1) + offset_px  # atlas position
    step = here - np.take(np.stack([start % w, start // w], axis=1), b, axis=0)
    offset = _matvec(jac, step)
    reach = 0.5 * _norm_axis1(offset) + 2.0 * np.take(jac_norm, b)
    target = np.take(position, b, axis=0) + offset
    prim, bu, bv, dist = g.rays.intersect(target + normal * reach[:, None], -normal)
    del target, normal, position
    hit = prim >= 0
    owner_mesh = np.full(prim.shape, -1)
    owner_mesh[hit] = g.rays.owner[prim[hit], 0]
    ok = hit & (owner_mesh == g.mesh_index) & (dist <= 2.0 * reach)
    # the rest for the points that landed on the skin only
    sel = np.flatnonzero(ok)
    m_idx, offset_px, partial, jac, here = (np.take(a, sel, axis=0) for a in (
        m_idx, offset_px, partial, jac, here))
    t_local = g.rays.owner[prim[sel], 1]
    bu, bv = bu[sel], bv[sel]
    corner = np.take(g.uv_corners, t_local, axis=0)
    xy = (corner[:, 0] * (1.0 - bu - bv)[:, None] + corner[:, 1] * bu[:, None]
          + corner[:, 2] * bv[:, None])  # finest texel coordinates
    del corner
    src_chart = g.tri_chart[t_local]
    # a point of a partly covered texel: its centre carried into the chart it landed on
    # (the offset o back through that chart's parameterization)
    at = np.flatnonzero(partial)
    inverse_jac = np.take(g.texels_per_scene_unit, t_local[at], axis=0)
    back = _matvec(np.take(jac, at, axis=0), np.take(offset_px, at, axis=0))
    xy[at] -= _matvec(inverse_jac, back)
    level_xy = (xy + 0.5) / scale - 0.5 + np.take(shift, src_chart, axis=0)
    own = src_chart == owner[m_idx]
    far = _norm_axis1(level_xy - (here - offset_px)) > 2.0
    ok = np.flatnonzero(~partial | ~own | far)
    return sel[ok], src_chart[ok], np.take(level_xy, ok, axis=0), t_local[ok]


_MARGIN_KERNEL = cl_source(__package__, "margins.cl")


def _device_coverage(device: Device, chart: NDArray[np.int32], triangle: NDArray[np.int32],
                     tri_chart: NDArray[np.int32], uv_corners: NDArray[np.float64]
                     ) -> NDArray[np.float32]:
    """:func:`texel_coverage` on the device (``texel_coverage`` kernel, a work item per
    texel, doubles in numpy's order: the same shares bit for bit; numpy's steps over the
    border texels took 1.25 s at texture 4096, before the layout's first level)."""
    h, w = chart.shape
    out = np.empty((h, w), np.float32)
    run_on_host_arrays(Kernel(_margin_program(device), "texel_coverage", 2), device, (w, h), (
        *(np.asarray(a, np.int32) for a in (chart, triangle, tri_chart)),
        np.asarray(uv_corners, np.float64), np.int32(h), np.int32(w)), (out,))
    return out


def _margin_program(device: Device) -> Any:
    return build(device, _MARGIN_KERNEL, [f"-DS={SEAM_SUBSAMPLES ** 2}"])


def margin_kernels(device: Device) -> tuple[Any, ...]:
    """The seam layout's kernels (margin points, read taps), for a
    :class:`~.opencl.Prewarm` (none on a device without doubles). Each call of them
    makes kernel objects of its own: levels and chunks run on several threads, and a
    kernel object's arguments are shared."""
    if not device.has_doubles:
        return ()
    program = _margin_program(device)
    return (*(Kernel(program, name, 1) for name in ("margin_rays", "margin_hits")),
            Kernel(program, "texel_coverage", 2))


def _device_points(g: SeamGeometry, level: int, shift: NDArray[np.int64],
                   owner: NDArray[np.int32], w: int, texels: _PointTexels,
                   frames: tuple[NDArray[Any], ...]
                   ) -> tuple[NDArray[np.int64], NDArray[np.int32], NDArray[np.float64],
                              NDArray[np.int64]]:
    """:func:`_numpy_points` with each point's arithmetic in two device kernels around
    the ray cast (numpy's steps over the points, each a pass over M x 3 doubles, were
    30% of the layout's time)."""
    if texels.sub.shape[0] != SEAM_SUBSAMPLES ** 2:
        raise InputError(f"margin points: {texels.sub.shape[0]} offsets a texel, the "
                         f"kernels take {SEAM_SUBSAMPLES ** 2}")
    rays_kernel, hits_kernel = margin_kernels(g.device)[:2]
    start, position, normal, jac_b, jac_norm = frames
    n = texels.count
    points = (texels.empty.astype(np.int64), texels.partial.astype(np.int64), texels.b,
              np.asarray(texels.sub, np.float64))
    origin, direction = np.empty((n, 3), np.float32), np.empty((n, 3), np.float32)
    reach = np.empty(n, np.float64)
    run_on_host_arrays(rays_kernel, g.device, (n,), (
        *points, start.astype(np.int64), position, normal, jac_b, jac_norm, np.int64(w),
        np.int32(texels.n_empty), np.int32(n)), (origin, direction, reach))
    prim, bu, bv, dist = g.rays.intersect(origin, direction)
    del origin, direction
    keep = np.empty(n, np.uint8)
    chart, t_local = np.empty(n, np.int32), np.empty(n, np.int64)
    level_xy = np.empty((n, 2), np.float64)
    device = g.device_buffers
    run_on_host_arrays(hits_kernel, g.device, (n,), (
        *points, jac_b, np.int64(w), np.int32(texels.n_empty), np.int32(n), prim, bu, bv,
        dist, reach, device["owner"], np.int64(g.mesh_index), device["corners"],
        device["inverse_jac"], device["tri_chart"], np.asarray(shift, np.int64), owner,
        np.float64(1 << level)), (keep, chart, level_xy, t_local))
    kept = np.flatnonzero(keep)
    return kept, np.take(chart, kept), np.take(level_xy, kept, axis=0), np.take(t_local, kept)


def _norm_axis1(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """``np.linalg.norm(a, axis=1)`` for a short axis 1, the same sums in the same order
    as columns added in turn (2-3x faster than numpy's reduction over it)."""
    squares = a[:, 0] * a[:, 0]
    for j in range(1, a.shape[1]):
        squares += a[:, j] * a[:, j]
    return np.sqrt(squares)


def _matvec(a: NDArray[np.float64], v: NDArray[np.float64]) -> NDArray[np.float64]:
    """(M, I): each (I, J) matrix of ``a`` times its J-vector of ``v``, as J products
    (einsum took 3x as long for these small shapes)."""
    out = a[:, :, 0] * v[:, 0:1]
    for j in range(1, a.shape[2]):
        out += a[:, :, j] * v[:, j:j + 1]
    return out


def _cell_frames(g: SeamGeometry, level: int, shift: NDArray[np.int64],
                 owner: NDArray[np.int32], cells: NDArray[np.int64], w: int
                 ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Per fully covered atlas texel in ``cells``: the surface point at its centre, the
    normal there and J = dP / d texel of its level (scene units), from the finest texel
    nearest its centre moved along that texel's triangle (exact where the surface is
    flat across the level texel)."""
    scale = 1 << level
    c = owner[cells]
    centre = (np.stack([cells % w, cells // w], axis=1) - np.take(shift, c, axis=0) + 0.5
              ) * scale - 0.5
    h0, w0 = g.triangle.shape
    f = np.clip(np.rint(centre).astype(np.int64), 0, [w0 - 1, h0 - 1])
    texel = f[:, 1] * w0 + f[:, 0]
    jac = np.take(g.jacobian, g.triangle.reshape(-1)[texel], axis=0)  # per finest texel
    position, normal = g.surface_at(texel)
    point = position + np.einsum("mij,mj->mi", jac, centre - f)
    normal = normal.astype(np.float64)
    normal /= np.maximum(_norm_axis1(normal), 1e-30)[:, None]
    return point, normal, jac * scale


def _mean_per_key(m: NDArray[np.int64], chart: NDArray[np.int32], xy: NDArray[np.float64],
                  n_charts: int) -> tuple[NDArray[np.int64], NDArray[np.float64],
                                          NDArray[np.int64]]:
    """One read per (texel ``m``, ``chart``): the texels, the mean of their positions
    ``xy`` and the first entry of each."""
    # np.unique's results by a packed integer sort (np.unique took 6.6 s of the
    # layout's threads' time at texture 4096, most of it its stable argsorts)
    first, inverse, counts = unique_keys(m * n_charts + chart)
    # each axis's sums into the means' own column, divided there: the stacked sums and
    # their quotient were two more arrays of them (0.24 GB for level 0's 7.9 M reads at
    # texture 4096, at a first render's peak)
    mean = np.empty((first.size, 2))
    for d in (0, 1):
        mean[:, d] = np.bincount(inverse, weights=xy[:, d])
        mean[:, d] /= counts
    del inverse
    return m[first], mean, first
