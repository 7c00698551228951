"""Texture-space diffusion across UV seams: each chart a tile of its own at every pyramid
level, with a margin of the surface across its borders (issue 19).

A blur in texture space sees a chart's neighbours only where the UV layout put them
side by side, which it never does across a seam: each chart was blurred alone, and in
shadowed skin the charts showed as patches (the demo face: 188 charts, the median
texel 1 mm from a chart border, 90% within 3 mm, while the widest terms reach 9 mm).
Here every chart gets, at each pyramid level k (a texel is 2^k finest texels), a tile:
its own texels (each the mean of the chart's finest texels under it, never another
chart's) and around them a margin as wide as that level's blurs reach. A margin texel m
takes the irradiance of the surface beyond the chart's border: the chart's
parameterization is extrapolated from its nearest texel b along the tangent plane
there, P = P_b + J_b (m - b), the point is projected onto the mesh along b's normal
(Embree), and the value is read at that point's texture coordinates in its own chart's
tile of the same level (the unfolding the issue asks for, done by projection rather
than by walking triangles: exact on a plane, and on a curved surface the margin follows
the surface under the tangent plane). The blurs run on these tile atlases unchanged; the
accumulation reads each finest texel's terms in its own chart's tiles.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..cache import kept, source_of
from ..device.choice import Device
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from .margins import (
    SeamGeometry,
    _device_coverage,
    _margin_sources,
)

TILE_GAP = 2
"""Texels of nothing between two tiles' margins: the recursive blur's tail beyond the
margin, e^(-x^2/2s^2) at x > 3 s, must not pick up the next tile's margin."""


def uv_charts(uv_tris: NDArray[Any], n_uv: int) -> tuple[NDArray[np.int32], int]:
    """The chart of each triangle (T,): connected components of the UV triangles through
    their shared UV corners (a seam splits the corners), and the number of charts. Kept
    in skinpipe's cache folder (:mod:`.kept`) by the UV triangles, scipy's version and
    the source of :func:`connected_uv_charts`, which makes them: importing scipy.sparse
    and its csgraph module took 0.32-0.34 s of CPU in every render, on the layout's
    thread beside the rays."""
    import scipy

    t = np.ascontiguousarray(uv_tris, dtype=np.int64).reshape(-1, 3)
    key = [scipy.__version__, source_of(connected_uv_charts), int(n_uv),
           hashlib.blake2b(t.tobytes(), digest_size=16).hexdigest()]

    def read(doc: dict[str, Any]) -> tuple[NDArray[np.int32], int]:
        chart, count = np.asarray(doc["chart"], np.int32), int(doc["count"])
        if chart.shape != (t.shape[0],) or (chart.size and (
                chart.min() != 0 or chart.max() != count - 1)):
            raise ValueError("kept charts do not fit the triangles")
        return chart, count

    def make() -> tuple[tuple[NDArray[np.int32], int], dict[str, Any]]:
        chart, count = connected_uv_charts(t, n_uv)
        return (chart, count), {"count": count, "chart": chart.tolist()}

    return kept("uv-charts", "charts", key, read, make)


def connected_uv_charts(uv_tris: NDArray[Any], n_uv: int) -> tuple[NDArray[np.int32], int]:
    """:func:`uv_charts` made: scipy's connected components of the graph of the UV
    triangles' edges."""
    from scipy.sparse import coo_matrix  # lazy: 0.2 s to import
    from scipy.sparse.csgraph import connected_components  # lazy: 0.27 s to import

    t = np.asarray(uv_tris, dtype=np.int64).reshape(-1, 3)
    rows = np.concatenate([t[:, 0], t[:, 1], t[:, 2]])
    cols = np.concatenate([t[:, 1], t[:, 2], t[:, 0]])
    graph = coo_matrix((np.ones(rows.size, np.int8), (rows, cols)), shape=(n_uv, n_uv))
    _, label = connected_components(graph, directed=False)
    used, chart = np.unique(label[t[:, 0]], return_inverse=True)
    return chart.astype(np.int32), int(used.size)


COVERAGE_SAMPLES = 4
"""Sub-samples a texel along each axis where a chart's border may cross it."""


def texel_coverage(device: Device | None, chart: NDArray[np.int32], triangle: NDArray[np.int32],
                   tri_chart: NDArray[np.int32], uv_corners: NDArray[np.float64]
                   ) -> NDArray[np.float32]:
    """Per covered texel (H, W) the share of its square its own chart's triangles
    cover: 1 inside a chart; at its border from COVERAGE_SAMPLES^2 sub-samples tested against
    the triangles of the same chart on the texel and its eight neighbours
    (``uv_corners``: texel coordinates). A rasteriser decides by the texel's centre, so
    a border texel stands for its whole square, part of which lies beyond a seam: what
    light falls there must come across the seam too (a pencil beside a seam lost 40% of
    what crosses it otherwise). On ``device`` where it has doubles, else (or None) in
    numpy: the same shares."""
    if chart.size and COVERAGE_SAMPLES == 4 and device is not None and device.has_doubles:
        return _device_coverage(device, chart, triangle, tri_chart, uv_corners)
    h, w = chart.shape
    cov = chart >= 0
    border = np.zeros_like(cov)
    pad = np.pad(chart, 1, constant_values=-1)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            border |= cov & (pad[1 + dy:1 + dy + h, 1 + dx:1 + dx + w] != chart)
    out = cov.astype(np.float32)
    ys, xs = np.nonzero(border)
    if ys.size == 0:
        return out
    own = chart[ys, xs]
    sub = (np.arange(COVERAGE_SAMPLES) + 0.5) / COVERAGE_SAMPLES - 0.5
    sx, sy = [a.ravel() for a in np.meshgrid(sub, sub)]
    # the triangles of the texel's own chart on it and its eight neighbours, each once
    # (neighbours mostly share triangles: a third of the tests at texture 4096)
    tpad = np.pad(triangle, 1, constant_values=-1)
    near = np.stack([tpad[1 + dy + ys, 1 + dx + xs] for dy in (-1, 0, 1) for dx in (-1, 0, 1)],
                    axis=1)
    near = np.where((near >= 0) & (tri_chart[np.maximum(near, 0)] == own[:, None]), near, -1)
    near.sort(axis=1)
    near[:, 1:][near[:, 1:] == near[:, :-1]] = -1
    row, col = np.nonzero(near >= 0)  # row-major: each texel's tests together
    q = uv_corners[near[row, col]]  # (P, 3, 2)
    e1, e2 = q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]
    det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
    det = np.where(np.abs(det) > 1e-12, det, np.inf)
    ddx = xs[row, None] + sx[None, :] - q[:, 0, 0:1]  # (P, S)
    ddy = ys[row, None] + sy[None, :] - q[:, 0, 1:2]
    b1 = (ddx * e2[:, 1:2] - ddy * e2[:, 0:1]) / det[:, None]
    b2 = (e1[:, 0:1] * ddy - e1[:, 1:2] * ddx) / det[:, None]
    hit = (b1 >= -1e-9) & (b2 >= -1e-9) & (b1 + b2 <= 1 + 1e-9)
    # the texel's own triangle is among them: every texel has at least one test
    inside = np.logical_or.reduceat(hit, np.searchsorted(row, np.arange(ys.size)), axis=0)
    # the centre itself is covered (the rasteriser said so): never below one sample
    out[ys, xs] = np.maximum(inside.sum(axis=1), 1) / sx.size
    return out


def chart_boxes(chart: NDArray[np.int32], n_charts: int) -> list[Any]:
    """Per chart of a chart map (H, W; -1: none) the bounding box of its texels, a pair of
    slices (``scipy.ndimage.find_objects``; None: no texel)."""
    from scipy.ndimage import find_objects  # lazy: 0.25 s to import

    return find_objects(chart + 1, max_label=n_charts)


@dataclass(frozen=True)
class SeamReads:
    """The reads across the seams of one level's tile atlas (:attr:`TileLevel.reads`):
    atlas texel t's reads are ``xy[rows[t]:rows[t + 1]]``, each the atlas position in
    another chart's tile that it reads with :func:`_bilinear_taps` (level 0) or
    :func:`_cubic_taps` (above). A read's taps and weights follow from its position, so
    a read is kept as its position: 8 bytes against a sparse matrix's 32 (4 taps) or
    128 (16), which held 0.96 GB of a 4096 render's 6.8 GB peak on the demo face."""

    shape: tuple[int, int]
    level: int
    rows: NDArray[np.int32]
    """(H W + 1,) each atlas texel's first read; its last read's end at the end."""
    xy: NDArray[np.float32]
    """(M, 2) the reads' atlas positions, texel by texel."""

    @property
    def count(self) -> int:
        return int(self.xy.shape[0])

    @cached_property
    def matrix(self) -> Any:
        """The reads as a sparse (H W, H W) matrix (scipy CSR): row t the weights with
        which atlas texel t reads the tiles' texels, each read's taps side by side. Made
        once, where the host reads across the seams (a device without doubles, every
        frame's fill) or a test compares with it."""
        from scipy.sparse import csr_matrix  # lazy: 0.2 s to import

        n = self.shape[0] * self.shape[1]
        index, weight = (_bilinear_taps if self.level == 0 else _cubic_taps)(
            self.xy, self.shape)
        indptr = self.rows.astype(np.int64) * index.shape[0]  # 4 or 16 taps a read
        return csr_matrix((np.ascontiguousarray(weight.T).ravel(),
                           np.ascontiguousarray(index.T).ravel(), indptr), shape=(n, n))


@dataclass
class TileLevel:
    """Pyramid level ``level`` as an atlas of chart tiles with ``margin`` texels around.

    A finest texel (x, y) of chart c sits in this atlas at ((x + 0.5) / 2^k - 0.5) +
    ``shift[c]`` (x and y alike)."""

    level: int
    margin: int
    shape: tuple[int, int]
    shift: NDArray[np.float32]
    """(C, 2): per chart, the atlas position of global level-k cell (0, 0)."""
    owner: NDArray[np.int32]
    """(H W,): the chart whose tile holds each atlas texel (-1: between the tiles).
    Each covered finest texel is splatted to the level-k cells of its chart's tile
    around its centre (level 0: its own; above: bilinearly, so its mass keeps its
    centre, where a cell's mean would move it to the cell's centre, up to
    (2^k - 1) / 2 finest texels): :func:`chart_splats`."""
    count: NDArray[np.float32]
    """Per atlas texel: the finest texels of its chart splatted to it, in texels (its
    coverage x 4^k; 0 outside the charts)."""
    reads: SeamReads
    """The surface across the seams: every tile texel its own chart does not cover in
    full (the margin's, and the chart's own border texels), within the margin and one of
    a texel it covers (:func:`_within_reach`), reads once per other chart:
    its centre carried across the seam into that chart's tile, read there with
    :func:`_bilinear_taps` (level 0) or :func:`_cubic_taps`."""
    mm_u: NDArray[np.float32] | None
    mm_v: NDArray[np.float32] | None
    """(H, W): mm of surface per atlas texel along u and v (a margin texel: its
    nearest tile texel's); None once a diffusion layout's level holds them as log2
    steps (``LevelGrid``)."""

    def read_across_seams(self, splatted: NDArray[np.float32]) -> NDArray[np.float32]:
        """``splatted`` (H W, 4: the tiles' own texels) with what each texel not covered
        in full reads across the seams added, in place (:attr:`reads`).

        The read adds coverage with the light, unnormalised: the two sides' splats of a
        texel a seam crosses are complementary parts of one cell, and a cubic read
        (:func:`_cubic_weights`) of a lattice as dense as the reader's hands on each
        texel's light whole. Reading the light per covered area instead (rgb / alpha)
        lost 31% of a pencil at a seam at levels 2-4: a splat's tent reaches past the
        border, where the reader does not look."""
        # read among the tiles' own texels only, before any margin is filled (16 taps a
        # read at 1.6 M reads: 0.9 s a fill as numpy gathers, 0.1 s as one product)
        splatted += self.reads.matrix @ splatted
        return splatted


_SEAM_READ_KERNEL = cl_source(__package__, "seam_reads.cl")


@lru_cache(maxsize=4)
def seam_read_kernel(device: Device) -> Any:
    """:data:`_SEAM_READ_KERNEL`'s kernel (one caller at a time: the diffusion's fill);
    None on a device without doubles (the host reads across the seams there)."""
    if not device.has_doubles:
        return None
    return Kernel(build(device, _SEAM_READ_KERNEL), "read_seams", 1)


def _bilinear_taps(xy: NDArray[np.float32], shape: tuple[int, int]
                   ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """(4, M) flat indices (int32: an atlas holds under 2^31 texels, :func:`tile_level`)
    and weights of bilinear reads at atlas positions ``xy``: at level 0, whose texels
    are boxes, the share of the read texel's square each texel's square overlaps (where
    the two lattices are aligned), so a read moves no light."""
    h, w = shape
    x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
    x0 = np.clip(np.floor(x).astype(np.int32), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(np.int32), 0, h - 2)
    ax, ay = np.clip(x - x0, 0.0, 1.0), np.clip(y - y0, 0.0, 1.0)
    i = y0 * w + x0
    return (np.stack([i, i + 1, i + w, i + w + 1]),
            np.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay]
                     ).astype(np.float32))


def _cubic_weights(t: NDArray[np.float64]) -> NDArray[np.float64]:
    """(4, M) Catmull-Rom weights of the texels at -1, 0, 1, 2 from the one below a
    fraction ``t`` (Keys 1981, a = -1/2): they sum to 1 and reproduce quadratics, so a
    read moves no light and widens nothing (a bilinear read adds 1/6 texel^2 per axis:
    the tail of a pencil's narrow terms across a seam came out 11% high at 0.8 mm). For
    the tent-splatted levels above 0, whose coverage is smooth across a border; a box
    texel's edge would ring (coverage 0.72-1.07 beside a seam at level 0)."""
    t2, t3 = t * t, t * t * t
    return np.stack([(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2,
                     (-3 * t3 + 4 * t2 + t) / 2, (t3 - t2) / 2])


def _cubic_taps(xy: NDArray[np.float32], shape: tuple[int, int]
                ) -> tuple[NDArray[np.int32], NDArray[np.float32]]:
    """(16, M) flat indices (int32, as :func:`_bilinear_taps`') and weights of
    Catmull-Rom reads at atlas positions ``xy``."""
    h, w = shape
    x, y = xy[:, 0].astype(np.float64), xy[:, 1].astype(np.float64)
    x0 = np.clip(np.floor(x).astype(np.int32), 1, w - 3)
    y0 = np.clip(np.floor(y).astype(np.int32), 1, h - 3)
    wx = _cubic_weights(np.clip(x - x0, 0.0, 1.0))
    wy = _cubic_weights(np.clip(y - y0, 0.0, 1.0))
    d = np.arange(-1, 3, dtype=np.int32)
    idx = ((y0[None, None, :] + d[:, None, None]) * w
           + x0[None, None, :] + d[None, :, None]).reshape(16, -1)
    return idx, (wy[:, None, :] * wx[None, :, :]).reshape(16, -1).astype(np.float32)


def _pack(sizes: NDArray[np.int64]) -> tuple[NDArray[np.int64], tuple[int, int]]:
    """Shelf packing of (C, 2) tile sizes (w, h), tallest first, TILE_GAP apart: each
    tile's (x, y) and the atlas (height, width)."""
    area = float((sizes + TILE_GAP).prod(axis=1).sum()) if sizes.size else 1.0
    width = max(int(sizes[:, 0].max(initial=1)) + TILE_GAP, int(math.sqrt(area * 1.1)) + 1)
    pos = np.zeros_like(sizes)
    x = y = row = 0
    for c in np.argsort(-sizes[:, 1], kind="stable"):
        tw, th = int(sizes[c, 0]), int(sizes[c, 1])
        if x + tw > width:
            x, y, row = 0, y + row + TILE_GAP, 0
        pos[c] = (x, y)
        x += tw + TILE_GAP
        row = max(row, th)
    return pos, (y + row, width)


def _phase_weights(level: int) -> NDArray[np.float64]:
    """(2^k, 2): along one axis, the bilinear weights of a finest texel to its first
    level-k cell and to the next, by its phase j in the cell's block: the texels whose
    first cell is g are x = g 2^k + 2^(k-1) + j, their fraction f = (j + 1/2) / 2^k."""
    s = 1 << level
    f = (np.arange(s) + 0.5) / s
    return np.stack([1.0 - f, f], axis=1)


def _splat_last_axis(values: NDArray[np.float64], first: int, level: int
                     ) -> tuple[int, NDArray[np.float64]]:
    """``values`` (..., L), finest texels ``first`` to ``first`` + L - 1 along the last
    axis, splatted bilinearly to level-k cells along it (level > 0; the first cell of
    texel x is floor((x + 0.5) / 2^k - 0.5)): (the first cell, (..., G) the sums over
    the cells it reaches). The texels
    are laid out in blocks of 2^k per first cell, and each block meets the weights of
    its phases in one product."""
    s = 1 << level
    first_cell = (2 * first + 1 - s) >> (level + 1)
    lead = (first + s // 2) % s  # the phase of texel ``first`` in its block
    n = values.shape[-1]
    blocks = -(-(lead + n) // s)
    padded = np.zeros((*values.shape[:-1], blocks * s))
    padded[..., lead:lead + n] = values
    both = padded.reshape(*values.shape[:-1], blocks, s) @ _phase_weights(level)
    out = np.zeros((*values.shape[:-1], blocks + 1))
    out[..., :-1] = both[..., 0]
    out[..., 1:] += both[..., 1]
    return first_cell, out


SPLAT_BAND_TEXELS = 1 << 19
"""Texels of a chart's bounding box :func:`chart_splats` takes at a time, in whole rows:
tens of MB of float64 intermediates however large the chart (one chart over most of a
4096 texture held 1 GB of them at level 1 as one piece)."""


def _box_bands(box: Any) -> Iterator[tuple[slice, slice]]:
    """A chart's bounding box (a pair of slices) in bands of whole rows of at most
    :data:`SPLAT_BAND_TEXELS` texels."""
    rows, columns = box
    step = max(1, SPLAT_BAND_TEXELS // (columns.stop - columns.start))
    for top in range(rows.start, rows.stop, step):
        yield slice(top, min(top + step, rows.stop)), columns


def _covered_share(chart: NDArray[np.int32], coverage: NDArray[np.float32] | None,
                   c: int, band: tuple[slice, slice]) -> NDArray[np.float32]:
    """Over ``band`` the share of each texel's square chart ``c`` covers (0 where the
    texel is another chart's or none)."""
    return np.where(chart[band] == c, np.float32(1) if coverage is None else coverage[band],
                    np.float32(0))


def _chart_cell_sums(chart: NDArray[np.int32], coverage: NDArray[np.float32] | None,
                     sizes: tuple[NDArray[Any], NDArray[Any]], c: int, box: Any,
                     level: int) -> tuple[int, int, NDArray[np.float64]]:
    """Chart ``c``'s finest texels in ``box`` splatted to its level-k cells (level > 0):
    (first cell row, first cell column, (3, rows, columns) sums of the covered share
    and of share x size along u and v), a band (:func:`_box_bands`) at a time, each
    band's cells added to the chart's (neighbouring bands share a row of them)."""
    s = 1 << level
    rows, columns = box
    first_y = (2 * rows.start + 1 - s) >> (level + 1)
    last_y = ((2 * (rows.stop - 1) + 1 - s) >> (level + 1)) + 1
    cells: NDArray[np.float64] | None = None
    first_x = 0
    for band in _box_bands(box):
        share = _covered_share(chart, coverage, c, band).astype(np.float64)
        sums = np.stack([share, share * sizes[0][band], share * sizes[1][band]])
        first_x, along_x = _splat_last_axis(sums, columns.start, level)
        band_y, part = _splat_last_axis(along_x.swapaxes(1, 2), band[0].start, level)
        if cells is None:
            cells = np.zeros((3, last_y - first_y + 1, part.shape[1]))
        cells[:, band_y - first_y:band_y - first_y + part.shape[2]] += part.swapaxes(1, 2)
    assert cells is not None  # a box has rows
    return first_y, first_x, cells


def chart_splats(chart: NDArray[np.int32], coverage: NDArray[np.float32] | None,
                 mm_u: NDArray[Any], mm_v: NDArray[Any], boxes: list[Any],
                 shift: NDArray[np.int64], level: int, shape: tuple[int, int]
                 ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """Per texel of a level-k tile atlas (``shape``; chart c's level-k cell g at g +
    ``shift[c]``) the bilinear splat's sums over the finest texels of its chart: (H W,)
    their splat weights x covered share (the count, in finest texels), and (2, H W)
    the weighted mean of their sizes in mm along u and v (0 where no texel reaches).

    Chart by chart over its bounding box (``boxes``, :func:`chart_boxes`) rather than a
    scatter of every finest texel: the bilinear splat is separable, a product per
    axis (:func:`_splat_last_axis`), and each chart's cells lie in its own tile. The
    products and sums in float64, where the scatter of every finest texel it replaced
    (``np.bincount``; tests/render/splat_reference.py, the reference it is tested
    against) rounded each product to float32: on the demo face at texture 4096 the
    means differ from its by up to 1.2e-7 of their value and the counts not at all, and
    its three splats of levels 0-4 took 3.5-4.0 s against 0.8-1.5 s here."""
    h, w = shape
    count = np.zeros((h, w), np.float32)
    mean_mm = np.zeros((2, h, w), np.float32)

    def put(c: int, first_y: int, first_x: int, weight: NDArray[np.float32],
            sizes: list[NDArray[Any]]) -> None:
        # a chart's cells lie in its own tile: no other chart's
        y0, x0 = first_y + int(shift[c, 1]), first_x + int(shift[c, 0])
        at = (slice(y0, y0 + weight.shape[0]), slice(x0, x0 + weight.shape[1]))
        count[at] = weight
        mean_mm[0][at], mean_mm[1][at] = sizes

    for c, box in enumerate(boxes):
        if box is None:
            continue
        if level == 0:  # each finest texel its own cell: its share, and its sizes
            for band in _box_bands(box):
                weight = _covered_share(chart, coverage, c, band)
                put(c, band[0].start, band[1].start, weight,
                    [np.where(weight > 0, m[band], np.float32(0)) for m in (mm_u, mm_v)])
            continue
        first_y, first_x, cells = _chart_cell_sums(chart, coverage, (mm_u, mm_v), c, box,
                                                   level)
        put(c, first_y, first_x, cells[0].astype(np.float32),
            [np.divide(cells[k], cells[0], out=np.zeros_like(cells[0]),
                       where=cells[0] > 0) for k in (1, 2)])
    return count.ravel(), mean_mm.reshape(2, -1)


def _nearest_own_texels(full: NDArray[np.bool_], inner: NDArray[np.bool_],
                        pos: NDArray[Any], sizes: NDArray[Any], empty: NDArray[np.bool_],
                        shape: tuple[int, int]) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
    """Every tile texel's nearest fully covered texel of its own chart (within its tile:
    where the extrapolation across the seam starts; a chart without one full cell: its
    partial ones), and the chart that owns it (-1: none). int32 (the atlas holds under
    2^31 texels): 0.3 GiB less at level 0 of texture 4096."""
    from scipy.ndimage import distance_transform_edt  # lazy: 0.25 s to import

    h, w = shape
    nearest = np.full(h * w, -1, np.int32)
    owner = np.full(h * w, -1, np.int32)
    # each tile a rectangle of the atlas: views of it, not (th, tw) flat indices, and
    # the transform's indices alone (its float64 distances are never read)
    tiles_of = [a.reshape(h, w) for a in (full, inner, nearest, owner)]
    for c in np.flatnonzero(~empty):
        x0, y0 = pos[c]
        tw, th = sizes[c]
        full_t, inner_t, nearest_t, owner_t = (a[y0:y0 + th, x0:x0 + tw] for a in tiles_of)
        mine = full_t if full_t.any() else inner_t
        if not mine.any():
            continue
        iy, ix = distance_transform_edt(~mine, return_distances=False, return_indices=True)
        nearest_t[...] = (iy + y0) * w + ix + x0
        owner_t[...] = c
    return nearest, owner


def tile_level(chart: NDArray[np.int32], n_charts: int, mm_u: NDArray[Any],
               mm_v: NDArray[Any], level: int, margin: int,
               geometry: SeamGeometry | None = None,
               coverage: NDArray[np.float32] | None = None,
               boxes: list[Any] | None = None) -> TileLevel:
    """Level ``level`` as a :class:`TileLevel`: ``chart`` (H, W) the chart of each finest
    texel (-1: none), ``mm_u``/``mm_v`` its size in mm ((H, W) maps, or what gives a
    box of them: :class:`~.texture_maps.TriangleStretch`), ``coverage`` the share of its
    square the chart covers (:func:`texel_coverage`; None: all of it); ``boxes``: the
    charts' :func:`chart_boxes`, when a caller keeps them for several levels. With
    ``geometry`` the margins, and the shares of texels a chart's border crosses, are
    filled with the surface across each chart's border (module docstring); without,
    they stay empty (each chart blurred alone)."""
    scale = 1 << level
    if boxes is None:
        boxes = chart_boxes(chart, n_charts)
    lo, hi, empty = _chart_cells(boxes, n_charts, level)
    sizes = np.where(empty[:, None], 0, hi - lo + 1 + 2 * margin)
    pos, shape = _pack(sizes)
    shift = pos + margin - lo  # atlas = global cell + shift
    h, w = shape
    n = h * w
    if n >= 2**31:
        raise InputError(f"a level-{level} tile atlas of {h} x {w} texels is beyond 2^31")
    # the coverage each atlas texel gathers and the mean size of its finest texels
    count, mean_mm = chart_splats(chart, coverage, mm_u, mm_v, boxes, shift, level, shape)
    inner = count > 1e-6
    full = count >= (1.0 - 1e-3) * float(4**level)
    nearest, owner = _nearest_own_texels(full, inner, pos, sizes, empty, shape)
    in_tile = owner >= 0
    outside = in_tile & ~inner
    reading = None  # the texels that read across the seams, where the level has margins
    if geometry is not None and margin > 0:
        # those a seam may cross (the margin and the chart's edge), within the blurs'
        # reach of the chart
        reading = in_tile & ~full & _within_reach(inner.reshape(h, w), margin + 1).ravel()
    # each axis's texel size, the mean of its finest texels' (mm), in place: the level's
    # arrays are held through its margin reads
    for mm in mean_mm:
        mm *= np.float32(scale)
        mm[outside] = mm[nearest[outside]]  # a margin texel: its nearest tile texel's
        typical = float(np.median(mm[inner])) if inner.any() else 1.0
        np.putmask(mm, ~in_tile, np.float32(typical))
    del in_tile, outside, inner
    mm_u_out, mm_v_out = (mm.reshape(h, w) for mm in mean_mm)
    del mean_mm
    index = np.zeros(0, np.int64)
    source = np.zeros((0, 2), np.float32)
    if geometry is not None and reading is not None:
        index, source = _margin_sources(geometry, level, shift, count, reading, full,
                                        nearest, owner, w)
    if source.shape[0] >= 2**31:
        raise InputError(f"{source.shape[0]} reads across the seams at level {level} are "
                         "beyond 2^31")
    # the reads come sorted by texel (_mean_per_key)
    rows = np.zeros(n + 1, np.int32)
    # summed into the int32 rows: no int64 sums (0.16 GB at level 0 of texture 4096)
    np.cumsum(np.bincount(index, minlength=n), out=rows[1:], dtype=np.int32)
    reads = SeamReads(shape, level, rows, source)
    return TileLevel(level, margin, shape, shift.astype(np.float32), owner, count, reads,
                     mm_u_out, mm_v_out)


def _within_reach(covered: NDArray[np.bool_], reach: int) -> NDArray[np.bool_]:
    """The atlas texels within ``reach`` texels along each axis of a ``covered`` one. A
    tile is its chart's bounding box grown by the margin, so many of its texels lie
    farther from the chart than that, in its corners and concavities (level 0 of the
    demo face at texture 4096: 6.0 M of its 9.8 M margin texels): there the level's
    widest blur carries less than its 3-sigma tail to the chart, and a read across the
    seam only fed texels no chart texel reads. A chart's texels are farther than
    ``reach`` (the margin and one) from any other tile: its own margin and TILE_GAP."""
    from scipy.ndimage import maximum_filter  # lazy, as tile_level's

    return maximum_filter(covered, size=2 * reach + 1, mode="constant")


def _chart_cells(boxes: list[Any], n_charts: int, level: int
                 ) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.bool_]]:
    """Per chart the lowest and highest level-k cell (x, y) its finest texels splat to,
    and which charts cover no texel (theirs 0 and -1): from each chart's bounding box
    of finest texels (:func:`chart_boxes`), as a texel's first cell grows with
    its position."""
    scale = 1 << level
    lo = np.zeros((n_charts, 2), np.int64)
    hi = np.full((n_charts, 2), -1, np.int64)
    empty = np.ones(n_charts, bool)
    for c, box in enumerate(boxes):
        if box is None:
            continue
        first = np.array([box[1].start, box[0].start], np.float64)
        last = np.array([box[1].stop - 1, box[0].stop - 1], np.float64)
        lo[c] = np.floor((first + 0.5) / scale - 0.5)
        hi[c] = np.floor((last + 0.5) / scale - 0.5) + 1
        empty[c] = False
    return lo, hi, empty
