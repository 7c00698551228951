"""The wide terms of the diffusion summed on the surface in 3D, not in its charts.

A tile's margin holds the surface across its chart's seams by extrapolating the chart
along its tangent plane (:mod:`.margins`): exact on a plane, and close where a term's
reach is small against the surface's radius. Red's widest terms reach 9 mm, beyond the
radius of a nose's tip or an ear's rim, where the tangent plane no longer follows the
surface and the light steps at chart borders (8.5% on a 10 mm sphere, 42% on a 5 mm one).
A term at least :data:`SURFACE_SIGMA_MM` wide is therefore summed over points on the
surface, which no chart border divides:

- the points: each chart's finest texels in blocks of ``2^level`` a side, a point at
  their area-weighted centroid (mm) carrying their area, mean normal, mean region
  weights and mean irradiance (a block's mean of a linear light sits at its centroid),
  the irradiance first blurred in the tiles by (h / 2)^2 (a box does not blur an edge
  on its border);
- step 1, per term: at each point, the normalised sum over the points of a Gaussian of
  the distance between them in 3D (as Jensen et al. 2001's BSSRDF is), times area and a
  facing weight (below); the terms of one block size are added there with the points'
  region weights;
- step 2, where the light is wanted (the camera's hits, or texels for a texture
  output): the normalised Gaussian over the points, as wide as their spacing h.

The blocks add h^2 / 12 to the variance, the pre-blur (h / 2)^2 and step 2 (0.7 h)^2;
step 1 takes them off. The profile was measured on a half-space; a point whose normal
turns from the receiver's lies off its plane, and less of its light arrives. Points
count fully to 60 degrees, not at all from 90 (the far side of a fold or an ear: that
light comes through the volume, :mod:`..light.thin_parts`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray
from scipy.ndimage import find_objects

from ..device.choice import Device
from ..device.memory import device_buffer
from ..device.programs import Kernel, build
from ..device.sources import cl_source

SURFACE_SIGMA_MM = 0.5
"""Terms at least this wide (sigma, mm) are summed on the surface: skin1's 0.72 mm term
blurred in the tiles stepped by 3.3% in green at the 5 mm sphere's seams."""
SPACINGS_A_SIGMA = 1.0
"""A term's points are at most sigma / this apart (the coarsest block size that keeps
it): the spheres' seams and terminators measure the same at sigma / h of 1-2 as of
2.3-3.3, and step 1 visits a fifth as many points."""
MAX_SPACING_MM = 1.5
"""...and at most this far apart: a block spans a large arc of a tight curve (3.2 mm of
a 5 mm sphere is 37 degrees), where its mean light sits off its centroid; red past
that sphere's terminator, against the path tracer: 1.22x with blocks of 3.2 mm, 1.10x
of 1.5 mm (an ear's rim or a nostril curves as tightly)."""
WIDTH_SPACINGS = 0.7
"""Step 2's Gaussian, in the points' spacings (its ripple over a regular lattice is
exp(-2 pi^2 0.7^2) = 6e-5): narrower than one spacing leaves more of the variance to
step 1, which follows the surface in 3D."""
REACH_SIGMAS = 5.0
"""Points farther than this many sigmas are left out (3.7e-6 of the peak): at 3 sigmas
the blue past the 5 mm sphere's terminator fell from 0.80 to 0.70-0.76 of the truth, at
4 red's light in a flat shadow was 0.948 of the light tracer's (limit 0.95)."""
CELLS_A_REACH = 2.0
"""The 3D grid's cells are the reach over this on a side."""
MAX_GRID_CELLS = 1 << 22
"""At most this many cells of the 3D grid (a coarser grid beyond: more points visited)."""
BAND_TEXELS = 1 << 20
"""Texels read at once while the points are made and filled (bounds their temporaries)."""
_KEY_BITS = 21  # block coordinates along u and v within a key (textures to 2^21 texels)

_SOURCE = cl_source(__package__, "surface_gather.cl")


@lru_cache(maxsize=4)
def _kernel(device: Device, name: str) -> Kernel:
    return Kernel(build(device, _SOURCE), name, 1)


def block_level(variance_mm2: float, texel_mm: float) -> int | None:
    """The block size (``2^level`` finest texels of ``texel_mm`` a side) whose points sum
    a term of ``variance_mm2`` on the surface, or None where the term stays in the
    charts' tiles: narrower than :data:`SURFACE_SIGMA_MM`, or than
    :data:`SPACINGS_A_SIGMA` texels."""
    sigma = math.sqrt(variance_mm2)
    ratio = min(sigma / SPACINGS_A_SIGMA, MAX_SPACING_MM) / texel_mm
    if sigma < SURFACE_SIGMA_MM or ratio < 1.0:
        return None
    return math.floor(math.log2(ratio))


@dataclass
class PointGrid:
    """Points sorted by the cell of a uniform 3D grid of side ``cell_mm`` (at least the
    reach), with each cell's first point (``start``)."""

    origin: NDArray[np.float32]
    cell_mm: float
    dims: tuple[int, int, int]
    order: NDArray[np.int64]
    start: NDArray[np.int32]

    @classmethod
    def of(cls, point_mm: NDArray[Any], reach_mm: float) -> PointGrid:
        p = np.asarray(point_mm, np.float64)[:, :3]
        lo, hi = p.min(axis=0), p.max(axis=0)
        side = max(reach_mm, 1e-6)
        dims = np.maximum(np.ceil((hi - lo) / side), 1).astype(np.int64)
        while int(dims.prod()) > MAX_GRID_CELLS:
            side *= 1.25
            dims = np.maximum(np.ceil((hi - lo) / side), 1).astype(np.int64)
        ijk = np.clip(np.floor((p - lo) / side).astype(np.int64), 0, dims - 1)
        key = (ijk[:, 2] * dims[1] + ijk[:, 1]) * dims[0] + ijk[:, 0]
        order = np.argsort(key, kind="stable")
        start = np.searchsorted(key[order], np.arange(int(dims.prod()) + 1)).astype(np.int32)
        return cls(lo.astype(np.float32), side, (int(dims[0]), int(dims[1]), int(dims[2])),
                   order, start)

    def args(self, device: Device) -> tuple[Any, ...]:
        return (device_buffer(device, self.start), *(np.float32(o) for o in self.origin),
                np.float32(1.0 / self.cell_mm), *(np.int32(d) for d in self.dims))


@dataclass
class SurfaceBlocks:
    """One block size's points on the surface."""

    level: int
    point: NDArray[np.float32]
    """(P, 4) centroid (mm, the scene's frame) and area (mm^2)."""
    normal: NDArray[np.float32]
    """(P, 4) unit mean normal."""
    region: NDArray[np.float32] | None
    """(P, R) mean region weights, summing to 1 (None: one region)."""
    spacing_mm: float
    """The blocks' side at the texture's 1% largest texels."""
    of_finest: NDArray[np.int64]
    """(finest blocks,) the block of each of the finest block size's blocks."""
    _grids: dict[float, PointGrid] = field(default_factory=dict)

    def grid(self, reach_mm: float) -> PointGrid:
        """The points on a 3D grid of side ``reach_mm`` (made once per reach)."""
        if reach_mm not in self._grids:
            self._grids[reach_mm] = PointGrid.of(self.point, reach_mm / CELLS_A_REACH)
        return self._grids[reach_mm]


@dataclass
class SurfacePoints:
    """A texture layout's covered texels taken to points on the surface, block size by
    block size (:func:`surface_points`)."""

    texel: NDArray[np.int32]
    """(N,) the covered texels (flat indices)."""
    weight: NDArray[np.float32]
    """(N,) the surface area each stands for (mm^2: its texel's times its chart's share)."""
    block: NDArray[np.int32]
    """(N,) each texel's block at the finest block size."""
    finest: int
    """The finest block size's level."""
    keys: NDArray[np.int64]
    """(finest blocks,) each block's chart and block coordinates."""
    sums: NDArray[np.float64]
    """(finest blocks, 7 + R) weight x (position (mm), normal, 1, region weights)."""
    texel_mm: float
    """The texture's 1% largest texels (mm)."""
    texel_surface: NDArray[np.float32] | None = None
    """(N, 2, 4) each texel's position (mm) and normal, kept for texture outputs."""
    _levels: dict[int, SurfaceBlocks] = field(default_factory=dict)

    def level(self, level: int) -> SurfaceBlocks:
        """The points of blocks of ``2^level`` texels a side (at least :attr:`finest`)."""
        if level not in self._levels:
            if level < self.finest:
                raise ValueError(f"blocks of level {level} are finer than the points' "
                                 f"finest ({self.finest})")
            shift = level - self.finest
            mask = (1 << _KEY_BITS) - 1
            by, bx = (self.keys >> _KEY_BITS) & mask, self.keys & mask
            key = ((self.keys >> (2 * _KEY_BITS)) << (2 * _KEY_BITS)) | \
                ((by >> shift) << _KEY_BITS) | (bx >> shift)
            _, of_finest = np.unique(key, return_inverse=True)
            of_finest = of_finest.ravel()
            n = int(of_finest.max()) + 1
            sums = np.stack([np.bincount(of_finest, weights=c, minlength=n)
                             for c in self.sums.T], axis=1)
            area = sums[:, 6]
            point = np.empty((n, 4), np.float32)
            point[:, :3] = sums[:, :3] / area[:, None]
            point[:, 3] = area
            normal = np.zeros((n, 4), np.float32)
            length = np.linalg.norm(sums[:, 3:6], axis=1, keepdims=True)
            normal[:, :3] = sums[:, 3:6] / np.where(length > 0, length, 1.0)
            region = None
            if sums.shape[1] > 7:
                r = sums[:, 7:]
                region = (r / np.maximum(r.sum(axis=1, keepdims=True), 1e-30)
                          ).astype(np.float32)
            self._levels[level] = SurfaceBlocks(level, point, normal, region,
                                                self.texel_mm * 2.0**level, of_finest)
        return self._levels[level]

    def means(self, level: int, per_texel: NDArray[Any]) -> NDArray[np.float64]:
        """(P, C) the area-weighted mean of ``per_texel`` (H x W, C) over each block of
        ``level``."""
        blocks = self.level(level)
        n0 = self.keys.size
        flat = per_texel.reshape(-1, per_texel.shape[-1])
        finest = np.zeros((n0, flat.shape[1]), np.float64)
        for s in range(0, self.texel.size, BAND_TEXELS):
            part = slice(s, s + BAND_TEXELS)
            v = flat[self.texel[part]] * self.weight[part, None]
            for c in range(flat.shape[1]):
                finest[:, c] += np.bincount(self.block[part], weights=v[:, c], minlength=n0)
        n = blocks.point.shape[0]
        sums = np.stack([np.bincount(blocks.of_finest, weights=finest[:, c], minlength=n)
                         for c in range(flat.shape[1])], axis=1)
        return sums / blocks.point[:, 3:4].astype(np.float64)


def _blocks(chart: NDArray[np.int32], texel: NDArray[np.int32], level: int
            ) -> tuple[NDArray[np.int32], NDArray[np.int64]]:
    """Each covered texel's block of ``2^level`` texels a side within its chart, and each
    block's key (chart, block row, block column): numbered within each chart's bounding
    box of blocks (scipy.ndimage.find_objects), the empty ones dropped. A sort of the
    keys took 1.8 s of 9.4 at texture 4096."""
    w = chart.shape[1]
    boxes = find_objects(chart + 1)
    n_charts = len(boxes)
    lo = np.zeros((n_charts, 2), np.int64)
    size = np.zeros((n_charts, 2), np.int64)
    for c, box in enumerate(boxes):
        if box is not None:
            lo[c] = (box[0].start >> level, box[1].start >> level)
            size[c] = ((box[0].stop - 1) >> level) - lo[c, 0] + 1, \
                ((box[1].stop - 1) >> level) - lo[c, 1] + 1
    offset = np.concatenate([[0], np.cumsum(size[:, 0] * size[:, 1])])
    c = chart.ravel()[texel]
    dense = offset[c] + (((texel // w) >> level) - lo[c, 0]) * size[c, 1] + \
        ((texel % w) >> level) - lo[c, 1]
    used = np.flatnonzero(np.bincount(dense, minlength=int(offset[-1])))
    number = np.zeros(int(offset[-1]), np.int32)
    number[used] = np.arange(used.size, dtype=np.int32)
    owner = np.searchsorted(offset, used, side="right") - 1
    local = used - offset[owner]
    by, bx = lo[owner, 0] + local // size[owner, 1], lo[owner, 1] + local % size[owner, 1]
    keys = (owner << (2 * _KEY_BITS)) | (by << _KEY_BITS) | bx
    return number[dense], keys


def surface_points(chart: NDArray[np.int32], share: NDArray[Any] | None, triangle: NDArray[Any],
                   jacobian_mm: NDArray[Any],
                   surface_at: Callable[[NDArray[np.int64]],
                                        tuple[NDArray[np.float32], NDArray[np.float32]]],
                   mm_per_unit: float, texel_mm: float, finest: int,
                   regions_at: Callable[[NDArray[np.int64], NDArray[Any]], NDArray[Any]]
                   | None = None, keep_texels: bool = False) -> SurfacePoints:
    """The covered texels of a chart map (``chart`` (H, W), -1 off the charts; ``share``
    the part of each texel its chart covers, None: all) as :class:`SurfacePoints` with
    blocks of ``2^finest`` texels: ``triangle`` the triangle map, ``jacobian_mm`` (T, 3, 2)
    dP / d texel in mm, ``surface_at`` the position (scene units of ``mm_per_unit`` mm)
    and normal at flat texel indices, ``regions_at`` the region weights (n, R) at flat
    texel indices of those triangles (None: one region). ``keep_texels``: keep each
    texel's position and normal (32 bytes a texel) for texture outputs."""
    texel = np.flatnonzero(chart.ravel() >= 0).astype(np.int32)
    tri = np.asarray(triangle).ravel()[texel]
    jac = np.asarray(jacobian_mm, np.float64)
    tri_area = np.linalg.norm(np.cross(jac[:, :, 0], jac[:, :, 1]), axis=1).astype(np.float32)
    weight = tri_area[tri]
    if share is not None:
        weight *= np.asarray(share, np.float32).ravel()[texel]
    block, keys = _blocks(chart, texel, finest)
    n0 = keys.size
    n_columns = 7 if regions_at is None else 7 + int(regions_at(texel[:1].astype(np.int64),
                                                                tri[:1]).shape[1])
    sums = np.zeros((n0, n_columns), np.float64)
    sums[:, 6] = np.bincount(block, weights=weight, minlength=n0)
    kept = np.empty((texel.size, 2, 4), np.float32) if keep_texels else None
    for s in range(0, texel.size, BAND_TEXELS):
        part = slice(s, s + BAND_TEXELS)
        position, normal = surface_at(texel[part].astype(np.int64))
        position *= np.float32(mm_per_unit)
        columns = [position, normal]
        if regions_at is not None:
            columns.append(regions_at(texel[part].astype(np.int64), tri[part]))
        at = 0
        for values in columns:
            for c in range(values.shape[1]):
                sums[:, at + (c if at < 6 else c + 1)] += np.bincount(
                    block[part], weights=values[:, c] * weight[part], minlength=n0)
            at += values.shape[1]
        if kept is not None:
            kept[part, 0, :3], kept[part, 1, :3] = position, normal
    return SurfacePoints(texel, weight, block, finest, keys, sums, texel_mm, kept)


TERMS_A_PASS = 4
"""Terms of one block size summed in one pass over the points (they share its reads)."""


def _terms_at_points(device: Device, blocks: SurfaceBlocks, value: NDArray[Any],
                     variances_mm2: list[float]) -> NDArray[np.float32]:
    """(K, P, 3) up to :data:`TERMS_A_PASS` terms (step 1) at ``blocks``' points from
    ``value`` (P, 3) there."""
    h = blocks.spacing_mm
    wd = WIDTH_SPACINGS * h
    inv, reach2 = np.zeros(4, np.float32), np.zeros(4, np.float32)
    for k, v in enumerate(variances_mm2):
        v_points = max(v - wd * wd - h * h / 12.0, 0.25 * v)
        inv[k], reach2[k] = 0.5 / v_points, REACH_SIGMAS**2 * v_points
    grid = blocks.grid(float(np.sqrt(reach2.max())))
    order = grid.order
    n, terms = order.size, len(variances_mm2)
    sorted_value = np.zeros((n, 4), np.float32)
    sorted_value[:, :3] = value[order]
    out = np.empty((n, 4, 4), np.float32)
    queue = device.queue
    # the buffers stay referenced until the queue is done: one of device_buffer's own
    # memory is unmapped when its last reference goes
    buffers = [device_buffer(device, np.ascontiguousarray(a)) for a in
               (blocks.point[order], blocks.normal[order], sorted_value)]
    grid_args = grid.args(device)
    out_buf = device_buffer(device, out.nbytes)
    vec = cl.cltypes.float4
    _kernel(device, "gather_on_surface")(
        queue, (n,), None, *buffers, np.int32(n), *grid_args,
        np.array(tuple(inv), vec), np.array(tuple(reach2), vec), np.int32(terms), out_buf)
    cl.enqueue_copy(queue, out, out_buf)
    queue.finish()
    del buffers, grid_args, out_buf
    result = np.empty((terms, n, 3), np.float32)
    result[:, order] = out[:, :terms, :3].transpose(1, 0, 2)
    return result


@dataclass
class LevelLight:
    """One block size's diffused light at its points, sorted for step 2."""

    point: NDArray[np.float32]
    normal: NDArray[np.float32]
    value: NDArray[np.float32]
    """(P, 4) the terms' weighted sum (RGB, 0)."""
    grid: PointGrid
    width_mm: float


@dataclass
class SurfaceLight:
    """The wide terms' light on the surface (:func:`surface_light`), read anywhere on it
    by :meth:`at`."""

    levels: list[LevelLight]
    flux: float
    """The light's flux: sum of area x value over points and channels (mm^2 x value)."""

    def at(self, device: Device, position_mm: NDArray[Any], normal: NDArray[Any]
           ) -> NDArray[np.float32]:
        """(N, 3) the light at surface points ``position_mm`` (N, 3) with unit
        ``normal`` (N, 3) (step 2)."""
        n = position_mm.shape[0]
        total = np.zeros((n, 3), np.float32)
        if n == 0 or not self.levels:
            return total
        at, facing = (np.zeros((n, 4), np.float32) for _ in range(2))
        at[:, :3], facing[:, :3] = position_mm, normal
        queue = device.queue
        at_buf, facing_buf = device_buffer(device, at), device_buffer(device, facing)
        out = np.empty((n, 4), np.float32)
        out_buf = device_buffer(device, out.nbytes)
        for lv in self.levels:
            reach = REACH_SIGMAS * lv.width_mm
            # referenced until the queue is done with them (see _term_at_points)
            buffers = [device_buffer(device, a) for a in (lv.point, lv.normal, lv.value)]
            grid_args = lv.grid.args(device)
            _kernel(device, "gather_at")(
                queue, (n,), None, at_buf, facing_buf, np.int32(n), *buffers, *grid_args,
                np.float32(0.5 / lv.width_mm**2), np.float32(reach * reach), out_buf)
            cl.enqueue_copy(queue, out, out_buf)
            queue.finish()
            del buffers, grid_args
            total += out[:, :3]
        return total

    def at_texels(self, device: Device, points: SurfacePoints, shape: tuple[int, ...]
                  ) -> NDArray[np.float32]:
        """(H, W, 3) of ``shape`` the light at the texels of ``points`` (made with
        their surface kept), 0 elsewhere."""
        surface = points.texel_surface
        if surface is None:
            raise ValueError("the points were made without their texels' surface")
        out = np.zeros((shape[0] * shape[1], 3), np.float32)
        for s in range(0, points.texel.size, BAND_TEXELS):
            part = slice(s, s + BAND_TEXELS)
            out[points.texel[part]] = self.at(device, surface[part, 0, :3],
                                              surface[part, 1, :3])
        return out.reshape(shape[0], shape[1], 3)


def surface_light(device: Device, points: SurfacePoints, irradiance: NDArray[Any],
                  variances_mm2: NDArray[Any], levels: list[int],
                  term_weights: NDArray[Any],
                  pre: dict[int, tuple[float, NDArray[Any]]] | None = None) -> SurfaceLight:
    """The terms of ``variances_mm2`` (K,), each summed with blocks of ``levels[k]``,
    weighted by ``term_weights`` (R, K, 3) per region and channel, of ``irradiance``
    (H, W, 3) on ``points``' surface."""
    tw = np.asarray(term_weights, np.float64)
    out: list[LevelLight] = []
    flux = 0.0
    for level in sorted(set(levels)):
        blocks = points.level(level)
        taken, source = (0.0, irradiance) if pre is None or level not in pre else pre[level]
        mean = points.means(level, source)
        total = np.zeros((mean.shape[0], 3), np.float64)
        here = [k for k, lv in enumerate(levels) if lv == level]
        for first in range(0, len(here), TERMS_A_PASS):
            batch = here[first:first + TERMS_A_PASS]
            per_term = _terms_at_points(device, blocks, mean,
                                        [float(variances_mm2[k]) - taken for k in batch])
            for k, term in zip(batch, per_term, strict=True):
                weight = tw[0, k] if blocks.region is None or tw.shape[0] == 1 else \
                    blocks.region.astype(np.float64) @ tw[:, k]
                total += weight * term
        flux += float((blocks.point[:, 3].astype(np.float64) @ total).sum())
        width = WIDTH_SPACINGS * blocks.spacing_mm
        grid = blocks.grid(REACH_SIGMAS * width)
        value = np.zeros((total.shape[0], 4), np.float32)
        value[:, :3] = total
        out.append(LevelLight(np.ascontiguousarray(blocks.point[grid.order]),
                              np.ascontiguousarray(blocks.normal[grid.order]),
                              np.ascontiguousarray(value[grid.order]), grid, width))
    return SurfaceLight(out, flux)


def texel_flux(points: SurfacePoints, rgb: NDArray[Any]) -> float:
    """The flux of a texture ``rgb`` (H, W, 3) over ``points``' texels, their true areas
    (mm^2 x value, channels summed)."""
    flat = rgb.reshape(-1, 3)
    return float(points.weight.astype(np.float64) @ flat[points.texel].sum(axis=1,
                                                                         dtype=np.float64))
