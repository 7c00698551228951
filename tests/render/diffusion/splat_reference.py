"""The splat of the finest texels into a level's chart tiles by its definition: a scatter
of every finest texel to its level-k cells with their bilinear weights (numpy's
``bincount``). The reference against which the layout's own splats
(:func:`skinpipe.render.chart_tiles.chart_splats`: separable, chart by chart) and the
diffusion's fill on the device (``splat_level``) are tested; it was the layout's own
until the twentieth session (3.5-4.0 s of its levels at texture 4096, against
0.8-1.5)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from skinpipe.render.diffusion.chart_tiles import TileLevel, chart_boxes


@dataclass(frozen=True)
class FinestTexels:
    """The covered finest texels of a chart map in row order (:func:`finest_texels`):
    their charts and covered shares, and each chart's bounding box. What :func:`fill`
    scatters from."""

    ys: NDArray[np.int64]
    xs: NDArray[np.int64]
    chart: NDArray[np.int64]
    share: NDArray[np.float32]
    """The share of each texel's square its chart covers (1 where no coverage map)."""
    boxes: list[Any]
    """Per chart its finest texels' bounding box (:func:`chart_boxes`)."""


def finest_texels(chart: NDArray[np.int32], n_charts: int,
                  coverage: NDArray[np.float32] | None = None) -> FinestTexels:
    """:class:`FinestTexels` of a chart map (H, W; -1: none) and the share of each texel
    its chart covers (``chart_tiles.texel_coverage``; None: all)."""
    ys, xs = np.nonzero(chart >= 0)
    share = np.ones(ys.size, np.float32) if coverage is None else \
        coverage[ys, xs].astype(np.float32)
    return FinestTexels(ys, xs, chart[ys, xs].astype(np.int64), share,
                        chart_boxes(chart, n_charts))


def _splat_table(level: int) -> NDArray[np.float32]:
    """(4^k, 4) the bilinear weights of a finest texel's four level-k cells by its phase
    in the cell (:func:`splat_geometry`): its centre at ((x + 0.5) / 2^k - 0.5) in cells, whose
    fraction depends on x mod 2^k alone (exactly: 2^k is a power of two)."""
    scale = 1 << level
    r = np.arange(scale * scale)
    fx = (r % scale + 0.5) / scale - 0.5
    fy = (r // scale + 0.5) / scale - 0.5
    fx, fy = fx - np.floor(fx), fy - np.floor(fy)
    return np.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy],
                    axis=1).astype(np.float32)


SPLAT_ROWS = 65536
"""Finest texels :func:`splat_geometry` works through at a time."""


def splat_geometry(finest: FinestTexels, shift: NDArray[np.int64], level: int, w: int
                   ) -> tuple[NDArray[np.int32], NDArray[np.uint16], NDArray[np.float32]]:
    """Per covered finest texel (:class:`FinestTexels`, row order) where it is splatted
    in a level-k atlas ``w`` texels wide whose charts sit at ``shift`` (atlas = global
    cell + shift): the flat index of the first of its cells (level 0: the one; above:
    it, the next, the one below and the next), its phase in the cell, (y mod 2^k) 2^k +
    x mod 2^k, which picks the weights (:func:`_splat_table`), and the share of its
    square its chart covers."""
    scale = 1 << level
    n = finest.ys.size
    base = np.empty(n, np.int32)
    phase = np.empty(n, np.uint16)
    shift = np.asarray(shift, np.int64)
    mask = scale - 1  # y mod 2^k and x mod 2^k of texels at y, x >= 0
    # in chunks whose temporaries stay in cache (whole arrays' took 0.3 s a level at
    # texture 4096, 0.86 s at the first, in fresh pages), and in integers: the first
    # cell, floor((x + 0.5) / 2^k - 0.5) = floor((2 x + 1 - 2^k) / 2^(k+1)), by an
    # arithmetic shift, which floors: the same cells as in floats
    for s in range(0, n, SPLAT_ROWS):
        part = slice(s, s + SPLAT_ROWS)
        ys, xs = finest.ys[part].astype(np.int64), finest.xs[part].astype(np.int64)
        cell_shift = np.take(shift, finest.chart[part], axis=0)
        gy = (2 * ys + (1 - scale)) >> (level + 1)
        gx = (2 * xs + (1 - scale)) >> (level + 1)
        base[part] = (gy + cell_shift[:, 1]) * w + gx + cell_shift[:, 0]
        phase[part] = (ys & mask) * scale + (xs & mask)
    return base, phase, finest.share


def _splat(base: NDArray[np.int32], phase: NDArray[np.uint16], share: NDArray[np.float32],
           level: int, shape: tuple[int, int], values: NDArray[Any]) -> NDArray[np.float64]:
    """(H W, D): per atlas texel (``shape``) the splat-weighted sum of ``values`` (N, D)
    over the finest texels splatted to it (:func:`splat_geometry`). One corner of the
    four at a time, each an accumulation at ``base`` shifted by the corner's offset: no
    (4, N) cells or weights are made (1.5 GB of temporaries at texture 4096)."""
    n = shape[0] * shape[1]
    at = base.astype(np.intp)
    if level == 0:  # the texel itself
        corners = [(0, share)]
    else:
        table = _splat_table(level)
        corners = [(off, table[:, j][phase] * share)
                   for j, off in enumerate((0, 1, shape[1], shape[1] + 1))]
    # a value's column and its sums in one piece each (strided (N, D) columns took a
    # third of the splat at texture 2048)
    columns = np.ascontiguousarray(np.asarray(values).T)
    out = np.empty((values.shape[1], n))
    # each corner's weighted values in one array for all: the product in the values'
    # precision as before, held as the doubles bincount sums (a product and bincount's
    # copy of it in doubles were 93 MB of fresh pages a corner at texture 4096)
    weighted = np.empty(at.size, np.float64)
    for d, column in enumerate(columns):
        for off, weight in corners:
            np.multiply(weight, column, out=weighted,
                        dtype=np.result_type(weight, column))
            summed = np.bincount(at, weights=weighted, minlength=n)
            if off == 0:  # the first corner: its sums as they are (bincount's are never
                out[d] = summed  # -0.0, so 0 + x would be x)
            else:
                out[d, off:] += summed[:n - off]  # a splat never reaches past the atlas
    return out.T


def fill(tiles: TileLevel, values: NDArray[np.float32], chart: NDArray[np.int32],
         coverage: NDArray[np.float32] | None) -> NDArray[np.float32]:
    """The atlas as RGBA (H, W, 4) float32 for a normalised convolution: rgb the sum
    of the chart's finest ``values`` (N covered, 3) under each texel over 4^k (E x
    coverage), alpha its coverage; to each texel not covered in full, what the other
    chart's tile holds (rgb and coverage alike) where its centre lies across the
    seam. ``chart`` and ``coverage``: those the tiles were made from
    (``chart_tiles.tile_level``). The diffusion splats on the device instead
    (``diffusion._fill_level``, then ``TileLevel.read_across_seams``, as here)."""
    h, w = tiles.shape
    area = float(4**tiles.level)
    out = np.empty((h * w, 4), np.float32)
    finest = finest_texels(chart, int(chart.max(initial=-1)) + 1, coverage)
    geometry = splat_geometry(finest, tiles.shift.astype(np.int64), tiles.level, w)
    out[:, :3] = _splat(*geometry, tiles.level, tiles.shape, values) / area
    out[:, 3] = tiles.count / area
    return tiles.read_across_seams(out).reshape(h, w, 4)
