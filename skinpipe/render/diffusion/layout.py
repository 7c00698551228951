"""The diffusion's layout: a pyramid of levels, each an atlas of chart tiles whose
margins hold the surface across the charts' seams (chart_tiles), made once per mesh,
UVs and texture size, filled with the irradiance by a splat and the reads across the
seams, and each term placed on the coarsest level where it is still wide enough."""

from __future__ import annotations

import ctypes
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from functools import lru_cache, partial
from typing import Any, NamedTuple

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device
from ..device.memory import (
    RowBands,
    device_buffer,
    host_buffer,
    host_output,
    in_bands,
    read_output,
)
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from ..surface.texture_maps import (
    REGION_WEIGHT_DTYPE,
    TexelRegions,
    at_texels,
    triangle_jacobians,
)
from .chart_tiles import (
    TileLevel,
    chart_boxes,
    seam_read_kernel,
    texel_coverage,
    tile_level,
    uv_charts,
)
from .inputs import _region_presence
from .margins import SeamGeometry
from .recursive_blur import (
    QUANTIZE_CHUNK,
    TABLE_MIN_SIGMA,
    iir_kernels,
    quantized_log2,
)
from .surface_terms import SurfacePoints, block_level, surface_points
from .tile_store import TileStore, drop_resident_pages, extremes

# ------------------------------------------- recursive, on per-chart tile pyramids

LEVEL_MIN_SIGMA_TEXELS = 2.0
"""A term is blurred on the coarsest pyramid level where its narrowest blur is still
this many of that level's texels: read back through a cubic B-spline (a Gaussian that
wide has no spectrum left at the level's Nyquist frequency, e^(-2 pi^2 sigma^2 / 4) <
1e-8), and each level down quarters the work; a chart tile's margin grows with the
widest blur its level keeps (4 texels: margins of 25 finest texels on the demo face,
3.0 M texels at level 0; 2: 13, 1.2 M)."""
MAX_LEVELS = 6
MARGIN_SIGMAS = 3.0
"""A chart tile's margin reaches this many of its level's widest blur's sigma (at the
1% smallest texels), plus a texel: the mass a Gaussian has beyond it is 1.1% in 2D,
which the normalised convolution spreads over what it does reach."""
MARGIN_TEXEL_QUANTILE = 0.01

_PYRAMID_KERNEL = cl_source(__package__, "pyramid.cl")


@lru_cache(maxsize=8)
def pyramid_kernels(device: Device, regions: int, by_triangle: bool = False
                    ) -> dict[str, Any]:
    """The accumulation kernel for ``regions`` region weights a texel (0: one region;
    ``by_triangle``: made again from the texel's triangle, :class:`TexelRegions`, rather
    than read from a map), and the one that splats the finest texels into a level's
    chart tiles.
    The jobs (their pyramid levels, whether to add to the output) are arguments, not
    compiled in: a program a batch cost a cold render a PoCL build (0.3 s) and a
    compilation per batch, for no measurable gain in the accumulation itself."""

    program = build(device, _PYRAMID_KERNEL, [
        f"-DREGIONS={regions}", f"-DBY_TRIANGLE={int(by_triangle and regions > 0)}"])
    return {"accumulate_terms": Kernel(program, "accumulate_terms", 2),
            "splat_level": Kernel(program, "splat_level", 2)}


def _added_variance_texels2(level: int) -> float:
    """Variance (finest texels^2, per axis) that reaching pyramid ``level`` and reading
    it back adds: each finest texel is splatted bilinearly to the level's cells around
    its centre, adding t (1 - t) level texels^2 at its phase t, over the 2^k phases
    (j + 1/2) / 2^k on average 1/6 + 1/(12 4^k), so 4^k / 6 + 1/12 finest texels^2;
    the cubic B-spline read back adds 1/3 level texel^2 at every phase, 4^k / 3."""
    if level == 0:
        return 0.0
    return 4.0**level / 2.0 + 1.0 / 12.0


def _max_level(h: int, w: int) -> int:
    """The coarsest pyramid level: halving while 8 texels remain, at most MAX_LEVELS."""
    k = 0
    while k + 1 < MAX_LEVELS and min(h, w) >> (k + 1) >= 8:
        k += 1
    return k


DIRECT_TEXEL_QUANTILE = 1e-4
DIRECT_TEXEL_MIN_COUNT = 8
"""The per-texel direct blur's radius is set by the chart texels' sizes from this
quantile up, and never by the DIRECT_TEXEL_MIN_COUNT smallest: one in 10^4 texels can
be far smaller than the rest (degenerate UV, on the demo face ten at 0.011 mm against
0.082 mm at this quantile and 0.105 mm median), and they would set a radius far wider
than every other texel needs; they are blurred as if they were the quantile's size
(narrower than their own sigma), and counted."""
TILE_BAND_BYTES = 32 << 20
"""The bytes of a stored level's mapped arrays a kernel reads at a time
(:meth:`LevelGrid.row_bands`)."""
LAYOUT_LEVELS_AT_ONCE = 2
"""Pyramid levels whose chart tiles :meth:`DiffusionLayout.prepare` makes side by side."""


class TexelSteps(NamedTuple):
    """One pyramid level's texel sizes for the per-texel direct blur."""

    u: NDArray[np.int32]
    """Steps (log2 grid of texel sizes) in use along u, from the
    :data:`DIRECT_TEXEL_QUANTILE` smallest up."""
    v: NDArray[np.int32]
    index_u: Any
    """Each texel's index into ``u`` (uint16 device buffer, row layout; texels smaller
    than the first step take it)."""
    index_v: Any
    smaller: int
    """How many texel sizes (u and v) lie below the first step."""


@dataclass(frozen=True)
class ChartLayout:
    """The UV layout's charts, for diffusion across seams: the chart of each texel (H, W;
    -1 off the charts), how many, and the surface the charts' margins are read from
    (None: none, each chart blurred alone)."""

    chart: NDArray[np.int32]
    n_charts: int
    geometry: SeamGeometry | None = None
    coverage: NDArray[np.float32] | None = None
    """(H, W): the share of each texel's square its chart covers
    (:func:`~.chart_tiles.texel_coverage`); None: all of it."""


def chart_layout(device: Device, maps: Any, points: NDArray[Any], tris: NDArray[np.int32],
                 uv: NDArray[Any], uv_tris: NDArray[np.int32], rays: Any,
                 mesh_index: int, mm_per_unit: float = 1.0) -> ChartLayout:
    """The charts of a UV layout rasterised into ``maps`` (a
    :class:`~.texture_maps.TextureMaps`) and the surface across their seams: the chart
    of each texel, each texel's covered share, and for the margins the ray scene
    ``rays`` (a :class:`~.raytrace.RayScene` holding the mesh as ``mesh_index``), each
    triangle's chart, UV corners (texels) and Jacobian, and each texel's triangle,
    position and normal (made from the triangles where tiles are made,
    :class:`~.texture_maps.TexelSurface`: the layout holds no position or normal map);
    ``mm_per_unit``: mm a scene unit."""
    tri_chart, n_charts = uv_charts(uv_tris, uv.shape[0])
    chart = at_texels(maps.triangle, tri_chart.astype(np.int32, copy=False), -1)
    corners, _, jacobian = triangle_jacobians(points, tris, uv, uv_tris.reshape(-1, 3),
                                              maps.size)
    geometry = SeamGeometry(device, rays, mesh_index, tri_chart, corners, jacobian,
                            maps.triangle, maps.texel_surface.at, mm_per_unit)
    return ChartLayout(chart, n_charts, geometry,
                       texel_coverage(device, chart, maps.triangle, tri_chart, corners))


def ranked_step(steps: NDArray[np.int32], rank: int) -> tuple[int, int]:
    """(the ``rank``-th smallest of ``steps`` (0-based), how many are smaller than it):
    ``np.partition(steps, rank)[rank]`` and a count, from one histogram of the steps
    (their span is a few octaves of 1024 steps), where the partition and the count took
    two passes over a copy of 7.7 M texels at texture 4096."""
    first = int(steps.min())
    cumulative = np.cumsum(np.bincount(np.subtract(steps, np.int32(first), dtype=np.int32)))
    at = int(np.searchsorted(cumulative, rank, side="right"))
    return first + at, int(cumulative[at - 1]) if at else 0


LEVEL_ARRAYS = ("typical", "uniform", "index_bounds", "index_u", "index_v", "steps_u",
                "steps_v", "texel_u", "texel_v", "smaller")
"""The arrays :meth:`LevelGrid.derived` gives and a LevelGrid is made from again."""


class LevelGrid:
    """One pyramid level as an atlas of chart tiles (:class:`~.chart_tiles.TileLevel`)
    with what its blurs need: texel sizes on the log2 grid as device indices (recursive
    and direct blur), whether the size is one everywhere, the typical size. With
    ``derived`` (:meth:`derived` of an earlier grid of the same tiles, read back from
    the tile store) those are taken as they are, not made from the texel sizes."""

    def __init__(self, device: Device, tiles: TileLevel,
                 derived: dict[str, NDArray[Any]] | None = None) -> None:
        self.device = device
        self.tiles = tiles
        self.level = tiles.level
        self.shape = tiles.shape
        self._index: tuple[int, int, int, int, Any, Any] | None = None
        self._index_arrays: tuple[NDArray[np.int32], NDArray[np.int32]] | None = None
        self._texel: TexelSteps | bool | None = False
        self._texel_arrays: tuple[NDArray[np.uint16], NDArray[np.uint16]] | None = None
        self._splat: tuple[Any, Any, Any] | None = None
        self._seams: tuple[Any, Any] | bool | None = None
        self.stored = derived is not None
        """Whether the tiles came from the tile store (mapped: :meth:`release_pages`)."""
        if derived is not None:
            self._take(derived)
            return
        inner = tiles.count.reshape(tiles.shape) > 0
        mm = [tiles.mm_u, tiles.mm_v]
        on = [m[inner] for m in mm] if inner.any() else [m.ravel() for m in mm]
        self.typical = [float(np.median(m)) for m in on]
        self.uniform = all(float(m.max() - m.min()) <= 1e-6 * float(m.max()) for m in on)
        self._q: tuple[NDArray[np.int32], ...] | None = tuple(quantized_log2(m) for m in mm)
        # the sizes live on as their log2 steps: the float copies go (8 bytes an atlas
        # texel, 0.23 GB over the levels at texture 4096, alive through the diffusion)
        tiles.mm_u = tiles.mm_v = None
        self._inner: NDArray[np.bool_] | None = inner

    def derived(self) -> dict[str, NDArray[Any]]:
        """What the level's blurs need of its texel sizes, as arrays (:data:`LEVEL_ARRAYS`,
        for the tile store; empty where a uniform level or steps past a uint16 need
        none): the typical sizes, whether uniform, the recursive blur's indices and the
        direct blur's steps, made now if they were not yet."""
        none = np.zeros(0, np.int32)
        out: dict[str, NDArray[Any]] = {
            "typical": np.asarray(self.typical, np.float64),
            "uniform": np.asarray([self.uniform], np.int8), "index_bounds": none,
            "index_u": none, "index_v": none, "steps_u": none, "steps_v": none,
            "texel_u": none.astype(np.uint16), "texel_v": none.astype(np.uint16),
            "smaller": np.zeros(1, np.int64)}
        if self.uniform:
            return out
        lo_u, hi_u, lo_v, hi_v, _, _ = self.index()
        assert self._index_arrays is not None
        out.update(index_bounds=np.asarray([lo_u, hi_u, lo_v, hi_v], np.int64),
                   index_u=self._index_arrays[0], index_v=self._index_arrays[1])
        texel = self.texel_steps()
        if texel is not None:
            assert self._texel_arrays is not None
            out.update(steps_u=texel.u, steps_v=texel.v, texel_u=self._texel_arrays[0],
                       texel_v=self._texel_arrays[1],
                       smaller=np.asarray([texel.smaller], np.int64))
        return out

    def _take(self, derived: dict[str, NDArray[Any]]) -> None:
        """:meth:`derived`'s arrays as this grid's, checked against its tiles' shape and
        each other (ValueError: a device kernel would read past them)."""
        h, w = self.shape
        typical, uniform = derived["typical"], derived["uniform"]
        if typical.shape != (2,) or uniform.shape != (1,):
            raise ValueError("a level grid's typical sizes or uniformity of another shape")
        self.typical = [float(t) for t in typical]
        self.uniform = bool(uniform[0])
        self._q = self._inner = None
        if self.uniform:
            return
        bounds, qu, qv = derived["index_bounds"], derived["index_u"], derived["index_v"]
        if bounds.shape != (4,) or qu.shape != (h, w) or qv.shape != (w, h) or \
                qu.dtype != np.int32 or qv.dtype != np.int32:
            raise ValueError("a level grid's blur indices of another shape")
        lo_u, hi_u, lo_v, hi_v = (int(b) for b in bounds)
        # the checks read the mapped arrays a chunk at a time, their pages let go after
        # each (a level's at once were 0.25 GB more at the irradiance's peak)
        for q, top in ((qu, hi_u - lo_u), (qv, hi_v - lo_v)):
            low, high = extremes(q) if q.size else (0, 0)
            if int(low) < 0 or int(high) > top:
                raise ValueError("a level grid's blur indices past their steps")
        self._index_arrays = (qu, qv)
        self._index = (lo_u, hi_u, lo_v, hi_v, host_buffer(self.device, qu),
                       host_buffer(self.device, qv))
        su, sv = derived["steps_u"], derived["steps_v"]
        if not su.size:  # steps past a uint16: the direct blur has no indices
            self._texel = None
            return
        tu, tv = derived["texel_u"], derived["texel_v"]
        if tu.shape != (h, w) or tv.shape != (h, w) or tu.dtype != np.uint16 or \
                tv.dtype != np.uint16 or su.ndim != 1 or sv.ndim != 1 or \
                int(extremes(tu)[1]) >= su.size or int(extremes(tv)[1]) >= sv.size:
            raise ValueError("a level grid's direct blur steps of another shape")
        self._texel_arrays = (tu, tv)
        self._texel = TexelSteps(su, sv, host_buffer(self.device, tu),
                                 host_buffer(self.device, tv), int(derived["smaller"][0]))

    def device_buffers(self) -> None:
        """Make every device buffer the level's fills and blurs read (each is otherwise
        made on first use): the splat's and seam reads', and for texel sizes that vary,
        the recursive and the direct blur's indices; then drop the texel sizes' log2
        steps those are made from (0.23 GB over the levels at texture 4096)."""
        self.splat_buffers()
        self.seam_buffers()
        if not self.uniform:  # a level of one texel size blurs without indices
            self.index()
            self.texel_steps()
        self._q = self._inner = None

    def release_pages(self) -> None:
        """Let the pages of the level's arrays that were mapped from the tile store go
        from this process's memory (:func:`~.tile_store.drop_resident_pages`; a kernel
        that reads them maps them back): after their check on loading, after the fill
        and after each of the level's blurs. Tiles made here are left alone."""
        t = self.tiles
        drop_resident_pages([t.owner, t.count, t.reads.rows, t.reads.xy,
                             *(self._index_arrays or ()), *(self._texel_arrays or ())])

    def row_bands(self, *arrays: NDArray[Any]) -> RowBands | None:
        """For tiles mapped from the store: bands of rows of ``arrays`` (each row-major
        with the same number of rows) of about :data:`TILE_BAND_BYTES` of them together,
        each band's pages let go once its kernel has run (None for tiles made here): the
        level-0 kernels of the demo face at texture 4096 read 80-160 MB of them each."""
        if not self.stored or not arrays or not arrays[0].size:
            return None
        rows = arrays[0].shape[0]
        total = sum(a.nbytes for a in arrays)

        def done(first: int, stop: int) -> None:
            drop_resident_pages([a[first:stop] for a in arrays])

        return RowBands(max(1, rows * TILE_BAND_BYTES // total), done)

    def splat_buffers(self) -> tuple[Any, Any, Any]:
        """Device buffers of the tiles' owners, counts and chart shifts (int2) for the
        ``splat_level`` kernel, made on first use (a CPU device reads them in place)."""
        if self._splat is None:
            t = self.tiles
            d = self.device
            self._splat = (host_buffer(d, t.owner), host_buffer(d, t.count),
                           host_buffer(d, np.rint(t.shift).astype(np.int32)))
        return self._splat

    def seam_buffers(self) -> tuple[Any, Any] | None:
        """Device buffers of the reads across the seams (:class:`~.chart_tiles.SeamReads`:
        each texel's first read, the reads' positions) for the ``read_seams`` kernel,
        made on first use; None on a device without doubles (the host reads them)."""
        if self._seams is None:
            reads = self.tiles.reads
            self._seams = False if seam_read_kernel(self.device) is None else \
                (host_buffer(self.device, reads.rows), host_buffer(self.device, reads.xy))
        return self._seams or None

    def index_arrays(self) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        """The arrays of :meth:`index`'s buffers (u in row layout, v transposed)."""
        self.index()
        assert self._index_arrays is not None
        return self._index_arrays

    def texel_arrays(self) -> tuple[NDArray[np.uint16], ...]:
        """The arrays of :meth:`texel_steps`' index buffers (none without them)."""
        self.texel_steps()
        return self._texel_arrays or ()

    def index(self) -> tuple[int, int, int, int, Any, Any]:
        """(lowest u step, highest u step, lowest v step, highest v step, u index buffer
        (int32, row layout), v index buffer (transposed)) of the texel sizes on the log2
        grid, for the recursive blur; made on first use."""
        if self._index is None:
            assert self._q is not None, "index() after device_buffers() dropped the steps"
            qu, qv = self._q
            lo_u, lo_v = int(qu.min()), int(qv.min())
            # each index made once, in the order the pass reads it, and read in place on
            # a CPU device (a copy, a transposed copy and the device's own copy were 0.4
            # GB of passing pages at level 0 of texture 4096, beside the irradiance)
            self._index_arrays = (np.subtract(qu, np.int32(lo_u), dtype=np.int32),
                                  np.subtract(qv.T, np.int32(lo_v), dtype=np.int32,
                                              order="C"))
            self._index = (lo_u, int(qu.max()), lo_v, int(qv.max()),
                           *(host_buffer(self.device, a) for a in self._index_arrays))
        return self._index

    def texel_steps(self) -> TexelSteps | None:
        """:class:`TexelSteps` for the per-texel direct blur, made on first use; None
        when the steps span more than a uint16 holds."""
        if self._texel is False:
            steps, lows, smaller = [], [], 0
            assert self._q is not None and self._inner is not None, \
                "texel_steps() after device_buffers() dropped the steps"
            for q in self._q:
                # the chart's own texels set the steps (a margin texel copies its nearest
                # one, a degenerate texel's size as often as it is nearest)
                on = (q[self._inner] if self._inner.any() else q).ravel()
                rank = min(max(int(DIRECT_TEXEL_QUANTILE * on.size), DIRECT_TEXEL_MIN_COUNT),
                           on.size - 1)
                lo, below = ranked_step(on, rank)
                steps.append(np.arange(lo, int(q.max()) + 1, dtype=np.int32))
                smaller += below
                del on
                lows.append(lo)
            if max(st.size for st in steps) > 65535:
                self._texel = None
            else:
                def index(q: NDArray[np.int32], lo: int) -> NDArray[np.uint16]:
                    flat = q.reshape(-1)  # max(q - lo, 0) as uint16
                    step = np.empty(flat.shape, np.uint16)
                    # a chunk at a time: the int32 difference stays in cache (whole
                    # arrays' were 0.1 GB of fresh pages per level 0 at texture 4096)
                    for s in range(0, flat.size, QUANTIZE_CHUNK):
                        part = np.subtract(flat[s:s + QUANTIZE_CHUNK], np.int32(lo),
                                           dtype=np.int32)
                        step[s:s + QUANTIZE_CHUNK] = np.maximum(part, 0, out=part)
                    return step.reshape(q.shape)

                tu, tv = (index(q, lo) for q, lo in zip(self._q, lows, strict=True))
                self._texel_arrays = (tu, tv)
                self._texel = TexelSteps(*steps, host_buffer(self.device, tu),
                                         host_buffer(self.device, tv), smaller)
        return self._texel  # type: ignore[return-value]


class DiffusionLayout:
    """What the diffusion of one texture layout needs besides the irradiance: coverage,
    region weights, the charts (:class:`ChartLayout`; without: every covered texel one
    chart) and, per pyramid level and margin, the charts' tile atlas
    (:class:`LevelGrid`, :mod:`.chart_tiles`). It depends on the UV layout and the
    texture size only, so a renderer makes it once and reuses it for every frame and
    light (:func:`diffuse_prepared`), and it keeps the work buffers: first touching
    fresh device memory costs PoCL about as much as a blur. With a ``store``
    (:class:`~.tile_store.TileStore`) the tiles are read from disk where another
    process made them, and written there where this one makes them.
    """

    def __init__(self, device: Device, mm_per_texel_u: NDArray[Any],
                 mm_per_texel_v: NDArray[Any],
                 coverage: NDArray[Any], region_weights: NDArray[Any] | None = None,
                 charts: ChartLayout | None = None, store: TileStore | None = None,
                 texel_regions: TexelRegions | None = None,
                 stretch: tuple[Any, Any] | None = None) -> None:
        cov = np.asarray(coverage, dtype=np.float32)
        if cov.ndim != 2:
            raise InputError(f"coverage must be (H, W), got {cov.shape}")
        h, w = cov.shape
        mm = [np.asarray(m, dtype=np.float32) for m in (mm_per_texel_u, mm_per_texel_v)]
        if any(m.shape != (h, w) for m in mm):
            raise InputError(f"coverage and mm-per-texel maps must be ({h}, {w})")
        self.device = device
        self.height, self.width = h, w
        self.region_weights = None if region_weights is None else \
            np.asarray(region_weights, dtype=REGION_WEIGHT_DTYPE)  # the maps' own: no copy
        if self.region_weights is not None and (self.region_weights.ndim != 3
                                                or self.region_weights.shape[:2] != (h, w)):
            raise InputError(f"region weights must be ({h}, {w}, R), "
                             f"got {self.region_weights.shape}")
        self.present = _region_presence(self.region_weights)
        self.region_shape = None if self.region_weights is None else self.region_weights.shape
        covered = cov > 0
        self.any_covered = bool(covered.any())
        if charts is None:
            charts = ChartLayout(np.where(covered, 0, -1).astype(np.int32), 1)
        elif charts.chart.shape != (h, w) or not np.array_equal(charts.chart >= 0, covered):
            raise InputError("the chart map must have a chart exactly where coverage is")
        self.charts = charts
        self._surface_released = False
        self.store = store
        self.levels = _max_level(h, w) + 1
        self._grids: dict[tuple[int, int], LevelGrid] = {}
        self._buffers: dict[str, Any] = {}
        self.surface: SurfacePoints | None = None
        """The covered texels as points on the surface, for the wide terms
        (:mod:`.surface_terms`; made by :meth:`prepare` while it holds the surface)."""
        # what the tiles read the texel sizes from: the maps, or where given boxes of
        # them made from the triangles (TextureMaps.triangle_stretch), so that the maps
        # need not outlive the irradiance (0.13 GB at texture 4096)
        self._mm: list[Any] | None = mm if stretch is None else list(stretch)
        if not self.any_covered:
            return
        on_chart = [m[covered] for m in mm]
        for name, m, mc in zip("uv", mm, on_chart, strict=True):
            if not (np.isfinite(mc).all() and mc.min() > 0):
                y, x = np.argwhere(covered & ~(np.isfinite(m) & (m > 0)))[0]
                raise InputError(f"mm per texel ({name}) must be finite and > 0 on covered "
                                 f"texels; texel ({x}, {y}) has {m[y, x]}")
        self.typical = [float(np.median(mc)) for mc in on_chart]
        # the level is chosen for the narrowest blur but for the 1% smallest texels
        self.coarse_mm = max(float(np.percentile(mc, 99.0)) for mc in on_chart)
        self.finest_mm = min(float(mc.min()) for mc in on_chart)
        # a tile's margin must reach the widest blur at its level's small texels
        self.small_mm = min(float(np.quantile(mc, MARGIN_TEXEL_QUANTILE)) for mc in on_chart)
        del on_chart
        self.iir = iir_kernels(device)
        self.cover_buf = host_buffer(device, cov)
        self.chart_buf = host_buffer(device, np.asarray(charts.chart, np.int32))
        # the part of each texel's square its chart covers, for the tiles' splat
        self.share_buf = host_buffer(device, covered.astype(np.float32)
                                     if charts.coverage is None else charts.coverage)
        self.n_regions = 0 if self.region_weights is None else self.region_weights.shape[2]
        # with the rasterizer's arrays each texel's region weights are made again where
        # the accumulation reads them: the layout does not hold the map (0.2 GB at
        # texture 4096 with six regions)
        tr = self._texel_regions = texel_regions
        self.by_triangle = bool(self.n_regions and tr is not None
                                and tr.triangle.shape == (h, w)
                                and tr.weights.shape[1:] == (self.n_regions,))
        if self.by_triangle:
            assert tr is not None
            self.region_args = tuple(host_buffer(device, a) for a in (
                tr.triangle, tr.frame, tr.corners, tr.weights))
            self.region_weights = None
        else:
            self.region_args = (host_buffer(device, self.region_weights if self.region_weights
                                            is not None else np.zeros(1, REGION_WEIGHT_DTYPE)),)

    def margin(self, level: int, sigma_mm: float) -> int:
        """Texels of margin a tile at ``level`` needs for a blur of ``sigma_mm`` (the
        largest of the level's jobs): :data:`MARGIN_SIGMAS` of it at the level's
        :data:`MARGIN_TEXEL_QUANTILE` smallest texels, plus one."""
        return math.ceil(MARGIN_SIGMAS * sigma_mm / (self.small_mm * 2.0**level)) + 1

    def term_level(self, variance: float) -> int:
        """The pyramid level a term of ``variance`` mm^2 is blurred on: the coarsest where
        its blur is still LEVEL_MIN_SIGMA_TEXELS of that level's texels, at the 1%
        largest texels."""
        sigma = math.sqrt(variance) / self.coarse_mm  # narrowest blur, finest texels
        k = 0
        while k + 1 < self.levels and sigma / 2 ** (k + 1) >= LEVEL_MIN_SIGMA_TEXELS:
            k += 1
        return k

    def level_margins(self, variances_mm2: NDArray[Any]) -> dict[int, int]:
        """Per pyramid level the tile margin the terms of ``variances_mm2`` blurred there
        need (:meth:`margin` of the widest; terms narrower than a quarter texel are not
        blurred)."""
        widest: dict[int, float] = {}
        for var in np.asarray(variances_mm2, dtype=np.float64).ravel():
            if math.sqrt(var) / self.finest_mm < TABLE_MIN_SIGMA:
                continue
            k = self.term_level(float(var))
            widest[k] = max(widest.get(k, 0.0), max(_job_sigma_mm(self, float(var), k)))
        return {k: self.margin(k, sg) for k, sg in widest.items()}

    def surface_levels(self, variances_mm2: NDArray[Any]) -> list[int | None]:
        """Per term of ``variances_mm2`` the block size its points are summed on the
        surface with (:func:`~.surface_terms.block_level`), None for a term blurred in
        the tiles (all of them where :meth:`prepare` made no points)."""
        surface = self.surface
        levels = [None if surface is None else block_level(float(v), self.coarse_mm)
                  for v in np.ravel(variances_mm2)]
        return [None if lv is None or surface is None or lv < surface.finest else lv
                for lv in levels]

    def pre_variance(self, level: int) -> float:
        """The blur (mm^2) the surface's points of blocks of ``2^level`` texels read the
        irradiance through: (h / 2)^2 for blocks h mm apart, as a block's box does not blur
        a hard edge on its border."""
        return (0.5 * self.coarse_mm * 2.0**level) ** 2

    def prepare(self, variances_mm2: NDArray[Any], texels_on_surface: bool = False) -> None:
        """Make the chart tiles the terms of ``variances_mm2`` need ahead of a diffusion
        (a renderer's layout task does, so that the frames' diffusion finds them), and
        the surface's points for the terms summed there (:mod:`.surface_terms`; with
        ``texels_on_surface`` each texel's position and normal too, for a texture
        output of the diffused light)."""
        v = np.ravel(variances_mm2).astype(np.float64)
        wide = [lv for lv in (block_level(float(x), self.coarse_mm) for x in v)
                if lv is not None]
        if wide and self.any_covered:
            self._make_surface(min(wide), texels_on_surface)
        levels = self.surface_levels(v)
        # the tiles blur the terms the surface does not sum, and the irradiance each
        # block size of points reads
        tiles = [float(x) for x, lv in zip(v, levels, strict=True) if lv is None] + \
            [self.pre_variance(lv) for lv in sorted({lv for lv in levels if lv is not None})]
        needed = sorted(self.level_margins(np.array(tiles, np.float64)).items()) \
            if self.any_covered else []
        wanted = [km for km in needed if self._made(*km) is None and not self._load(*km)]
        if wanted and self._surface_released:
            raise RuntimeError(f"the layout's surface was let go (release_surface): no new "
                               f"tiles (levels, margins {wanted}) can be made")
        if wanted:
            # two levels at once: each level's single-threaded parts (splats, distance
            # transforms, read taps) run beside the other's ray casts (a quarter off the
            # layout's time, for 0.24 GB more peak memory at texture 2048)
            c = self.charts
            boxes = chart_boxes(c.chart, c.n_charts)

            def make(level: int, margin: int) -> None:
                self.grid(level, margin, boxes)
                release_freed_heap()  # before the next level's intermediates

            with ThreadPoolExecutor(LAYOUT_LEVELS_AT_ONCE) as pool:
                list(pool.map(lambda km: make(*km), wanted))
        for km in needed:
            # the blurs' device buffers too, here beside the irradiance rather than in
            # the diffusion after it (texture 4096: 1.1 s of a 9 s diffusion)
            self.grid(*km).device_buffers()

    def _make_surface(self, finest: int, texels: bool) -> None:
        """:attr:`surface` with blocks of ``2^finest`` texels (kept where it has them,
        and the texels' surface if ``texels`` asks for it), while the geometry is held."""
        s = self.surface
        if s is not None and s.finest <= finest and (s.texel_surface is not None or
                                                     not texels):
            return
        geometry = self.charts.geometry
        if geometry is None:
            return  # no surface (a layout without one, or let go): the tiles blur all
        regions_at = None
        tr = self._texel_regions
        if self.by_triangle and tr is not None:
            # a triangle's mean: the points average blocks of texels anyway
            per_triangle = tr.weights[tr.corners].mean(axis=1, dtype=np.float32)

            def regions_at(texel: NDArray[np.int64], tri: NDArray[Any]) -> NDArray[Any]:
                return per_triangle[tri]
        elif self.region_weights is not None:
            flat = self.region_weights.reshape(-1, self.region_weights.shape[2])

            def regions_at(texel: NDArray[np.int64], tri: NDArray[Any]) -> NDArray[Any]:
                return flat[texel].astype(np.float32)
        mm = geometry.mm_per_unit
        self.surface = surface_points(
            self.charts.chart, self.charts.coverage, geometry.triangle,
            geometry.jacobian * mm, geometry.surface_at, mm, self.coarse_mm, finest,
            regions_at, texels)

    def grid(self, level: int, margin: int, boxes: list[Any] | None = None) -> LevelGrid:
        """Level ``level``'s chart tiles with at least ``margin`` texels around each, made
        on first use (:func:`~.chart_tiles.tile_level`; ``boxes``: the charts'
        :func:`~.chart_tiles.chart_boxes`, when the caller has them)."""
        key = self._made(level, margin)
        if key is None and self._load(level, margin):
            key = self._made(level, margin)
        if key is None:
            c = self.charts
            if c.geometry is None and self._surface_released:
                raise RuntimeError(f"the layout's surface was let go (release_surface): no "
                                   f"new tiles (level {level}, margin {margin}) can be made")
            assert self._mm is not None
            tiles = tile_level(c.chart, c.n_charts, self._mm[0], self._mm[1], level, margin,
                               c.geometry, c.coverage, boxes)
            key = (level, margin)
            grid = self._grids[key] = LevelGrid(self.device, tiles)
            if self.store is not None:  # with what its blurs need of the texel sizes
                self.store.save(tiles, grid.derived())
        return self._grids[key]

    def release_surface(self) -> None:
        """Let the surface the margins are read from go (the ray scene and the
        triangles), and the stretch maps the tiles are made from, once the tiles every
        diffusion to come needs are made: a render's last frame. Asking for other tiles
        then is an error."""
        self.charts = replace(self.charts, geometry=None)
        self._surface_released = True
        self._mm = None  # no tiles are made any more: the stretch maps may go too

    def release_work(self) -> None:
        """Let the diffusions' work buffers and level tiles go (the atlases' scratch and
        source alone are 0.6 GB at texture 4096): a render's last diffusion is done,
        and what follows it (the push-pull, the shading) allocates its own. A later
        diffusion makes them again (tiles from the store, else from the surface if it
        is still held)."""
        self._buffers.clear()
        self._grids.clear()

    def _load(self, level: int, margin: int) -> bool:
        """Whether the store (if any) held tiles for (``level``, ``margin``), now made a
        level of this layout."""
        grid = None if self.store is None else self.store.load(
            level, margin, partial(LevelGrid, self.device))
        if grid is None:
            return False
        self._grids[(level, grid.tiles.margin)] = grid
        grid.release_pages()  # its checks read every page; the kernels read some
        return True

    def _made(self, level: int, margin: int) -> tuple[int, int] | None:
        """The key of tiles already made that serve (``level``, ``margin``), if any: a
        wider margin holds what a narrower one would (more texels blurred, the same
        light), so a second set of terms (one profile for all regions) reuses them."""
        wider = [m for (k, m) in self._grids if k == level and m >= margin]
        return (level, min(wider)) if wider else None

    def buffer(self, name: str, nbytes: int) -> Any:
        """A device work buffer of at least ``nbytes``, kept for the next diffusion of
        this layout."""
        if name not in self._buffers or self._buffers[name].size < nbytes:
            self._buffers.pop(name, None)  # its memory goes before the larger one comes
            self._buffers[name] = device_buffer(self.device, nbytes)
        return self._buffers[name]


def release_freed_heap() -> None:
    """Hand the memory the C heap keeps after freeing back to the system (glibc's
    ``malloc_trim``; a no-op elsewhere). The layout's threads free gigabytes of
    intermediates of under 32 MB each, which glibc keeps in per-thread arenas for the
    next allocation there: the diffusion that follows allocates on the main thread and
    the kept memory stays on top of it (as Dask's workers trim theirs). The renderer
    calls it too before a diffusion: the main thread's own arenas held 0.18 GB freed by
    the irradiance at texture 4096 (12 ms to hand back)."""
    try:
        libc = ctypes.CDLL(None)
        trim = libc.malloc_trim
    except (OSError, AttributeError, TypeError):  # no glibc (musl, macOS, Windows)
        return
    trim(0)


def _fill_level(layout: DiffusionLayout, grid: LevelGrid, irradiance: Any, scratch: Any,
                into: Any) -> Any:
    """``grid``'s tile atlas filled with ``irradiance`` (a device buffer of the RGB per
    finest texel, which the splat reads as (E, 1); tests/render/splat_reference.py's
    ``fill`` is its reference): the splat on the device (``splat_level``: numpy's
    accumulations took half of a 4096 diffusion, 4.8 of 12 s) into ``scratch``, then
    the reads across the seams from there into ``into`` (``read_seams``), which it
    returns; on a device without doubles the host reads across the seams and the atlas
    goes into ``into`` as well. ``scratch`` and ``into``: device buffers of at least the
    atlas (float4). Host memory a device on this machine reads in place."""
    device = layout.device
    kernel = pyramid_kernels(device, layout.n_regions)["splat_level"]
    queue = device.queue
    lh, lw = grid.shape
    reads = grid.seam_buffers()
    out = np.empty((lh * lw, 4), np.float32) if reads is None else None
    splat_into = scratch if out is None else host_output(device, out)
    args = (irradiance, layout.share_buf, layout.chart_buf, *grid.splat_buffers(), splat_into,
            np.int32(layout.width), np.int32(layout.height), np.int32(lw), np.int32(lh),
            np.int32(grid.level))
    t = grid.tiles
    in_bands(queue, grid.row_bands(t.owner.reshape(lh, lw), t.count.reshape(lh, lw)), lh, 1,
             lambda first, stop: kernel(queue, (lw, stop - first), None, *args,
                                        global_offset=(0, first)))
    if out is not None:
        read_output(device, splat_into, out)
        # into ``into``, which outlives the kernels that read the atlas: a buffer over
        # this function's array let the array go with the caller's last reference while
        # a blur or the terms' sum still read it (a band of texels came out black)
        cl.enqueue_copy(queue, into, grid.tiles.read_across_seams(out))
        return into
    # the reads on the device too: scipy's product ran on one core (0.45 s of a 2.8 s
    # diffusion at texture 2048), the kernel on all, the same sums
    args = (*reads, np.int32(lh), np.int32(lw), np.int32(grid.level > 0), scratch,
            np.int32(lh * lw), into)
    # a band of atlas rows at a time for stored tiles: their reads' rows and positions
    rows, xy = t.reads.rows, t.reads.xy
    bands = RowBands(max(1, lh * TILE_BAND_BYTES // (rows.nbytes + xy.nbytes)),
                     lambda a, b: drop_resident_pages([
                         rows[a * lw:b * lw + 1], xy[int(rows[a * lw]):int(rows[b * lw])]])
                     ) if grid.stored else None
    in_bands(queue, bands, lh, 1, lambda first, stop: seam_read_kernel(device)(
        queue, ((stop - first) * lw,), None, *args, global_offset=(first * lw,)))
    return into


def _release_level(queue: Any, grid: LevelGrid) -> None:
    """For tiles mapped from the store: wait for ``queue``, then let ``grid``'s pages go
    (:meth:`LevelGrid.release_pages`), after the level's fill and after each of its
    blurs, so that the diffusion holds only what its kernel at work reads of the tiles
    (the demo face at texture 4096: 0.77 GB of mapped tiles, 0.52 GB of them level
    0's; its one recursive blur there reads 0.15 GB of them, its direct ones 0.08)."""
    if grid.stored:
        queue.finish()
        grid.release_pages()


def _job_sigma_mm(layout: DiffusionLayout, variance: float, k: int) -> list[float]:
    """Per axis the blur's sigma in mm for a term of ``variance`` mm^2 at pyramid level
    ``k``: less what reaching the level and reading it back add."""
    return [math.sqrt(max(variance - _added_variance_texels2(k) * t**2, 1e-30))
            for t in layout.typical]
