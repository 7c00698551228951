"""Push-pull hole filling of texture maps (Gortler et al. 1996, "The Lumigraph", sec. 3.4).

Texels outside the charts are filled from their surroundings so that bilinear lookups
near a seam never blend in black: a pyramid of coverage-weighted 2 x 2 sums (pull),
then each level's empty texels take their coarser parent's normalised value (push).
Covered texels are returned unchanged. :func:`push_pull` runs on the OpenCL device;
:func:`push_pull_reference` is the numpy version it is tested against.

The pyramid's fill is an average over the neighbourhood in UV space, which near a chart
can hold other charts (other places on the face, lit differently). A bilinear lookup
at a point near a chart's edge reads gutter texels, so :func:`dilate_charts` then gives
the texels within :data:`GUTTER_RING` of a chart its nearest covered texel's value: the
lookups see only their own chart (the demo's bright texels at chart borders, issue 19).
For smooth fields (the irradiance, the diffused light) :func:`extrapolate_charts` then
continues each chart's values linearly into the texels next to it, so that a lookup near
a chart's edge reads what the chart's own slope says: a copy there is off by the slope
over a texel, and on a sphere past the terminator that stepped by 1-3% at every seam.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device, or_default
from ..device.memory import device_buffer, host_buffer, host_output, read_output
from ..device.programs import Kernel, build
from ..device.sources import cl_source


def _checked(values: NDArray[Any], coverage: NDArray[Any]
             ) -> tuple[NDArray[np.float32], NDArray[np.float32], bool]:
    """(H, W, C) float32 values, (H, W) coverage, and whether the values were (H, W)."""
    v = np.asarray(values, dtype=np.float32)
    c = np.asarray(coverage, dtype=np.float32)
    squeeze = v.ndim == 2
    if squeeze:
        v = v[..., None]
    if v.ndim != 3 or c.shape != v.shape[:2]:
        raise InputError(f"push-pull: values (H, W[, C]) and coverage (H, W) must match, "
                         f"got {np.shape(values)} and {np.shape(coverage)}")
    return v, c, squeeze


def push_pull_reference(values: NDArray[Any], coverage: NDArray[Any]) -> NDArray[np.float32]:
    """:func:`push_pull` in numpy (one thread): the reference for its tests."""
    v, c, squeeze = _checked(values, coverage)
    levels = [(v * c[..., None], c)]
    while min(levels[-1][1].shape) > 1:
        pv, pc = levels[-1]
        h, w = pc.shape
        if h % 2 or w % 2:
            pv = np.pad(pv, ((0, h % 2), (0, w % 2), (0, 0)))
            pc = np.pad(pc, ((0, h % 2), (0, w % 2)))
        sv = pv[0::2, 0::2] + pv[1::2, 0::2] + pv[0::2, 1::2] + pv[1::2, 1::2]
        sc = pc[0::2, 0::2] + pc[1::2, 0::2] + pc[0::2, 1::2] + pc[1::2, 1::2]
        levels.append((sv, sc))
    # normalised colours per level, each level's holes filled from the coarser one
    filled = levels[-1][0] / np.maximum(levels[-1][1], 1e-30)[..., None]
    for sv, sc in reversed(levels[1:-1]):
        up = np.repeat(np.repeat(filled, 2, axis=0)[:sc.shape[0]], 2, axis=1)[:, :sc.shape[1]]
        filled = np.divide(sv, sc[..., None], out=up, where=sc[..., None] > 0)
    if len(levels) > 1:
        h, w = c.shape
        filled = np.repeat(np.repeat(filled, 2, axis=0)[:h], 2, axis=1)[:, :w]
    out = np.where(c[..., None] > 0, v, filled).astype(np.float32, copy=False)
    return out[..., 0] if squeeze else out


_KERNEL = cl_source(__package__, "push_pull.cl")


@lru_cache(maxsize=4)
def push_pull_kernels(device: Device) -> tuple[Any, Any, Any]:
    program = build(device, _KERNEL)
    return tuple(Kernel(program, name, dims)
                 for name, dims in (("pull", 2), ("push", 2), ("normalise", 1)))


def push_pull(values: NDArray[Any], coverage: NDArray[Any], in_place: bool = False,
              device: Device | None = None) -> NDArray[np.float32]:
    """Fill texels outside the charts (``coverage`` 0) of (H, W[, C]) ``values`` from
    their surroundings, on the OpenCL device; covered texels are returned unchanged.
    The same maps as :func:`push_pull_reference` within float32 rounding. ``in_place``:
    the result goes into ``values`` itself where it is float32 and C-contiguous (a
    caller done with them: a texture-sized array less, 0.2-0.27 GB at texture 4096),
    else into a new array; either way it is returned. ``device``: where it runs (None:
    :func:`~..device.choice.or_default`)."""
    device = or_default(device)
    pull, push, normalise = push_pull_kernels(device)
    v, c, squeeze = _checked(values, coverage)
    in_place = in_place and v.flags.c_contiguous and np.may_share_memory(v, values)
    queue = device.queue
    h, w, ch = v.shape
    shapes = [(h, w)]
    while min(shapes[-1]) > 1:
        shapes.append(((shapes[-1][0] + 1) // 2, (shapes[-1][1] + 1) // 2))
    if len(shapes) == 1:  # a single row or column: nothing coarser to fill from
        out = np.where(c[..., None] > 0, v, np.float32(0.0))
        return out[..., 0] if squeeze else out
    out = v if in_place else np.empty(v.shape, np.float32)  # C order whatever v's
    out_buf = host_output(device, out)
    # in place, the finest level's push reads and writes one buffer (a texel reads only
    # itself, as on the coarser levels)
    levels = [(out_buf if in_place else host_buffer(device, v), host_buffer(device, c))]
    for k in range(1, len(shapes)):
        (sh, sw), (dh, dw) = shapes[k - 1], shapes[k]
        levels.append((device_buffer(device, dh * dw * ch * 4),
                       device_buffer(device, dh * dw * 4)))
        pull(queue, (dw, dh), None, *levels[k - 1], *levels[k], np.int32(sw), np.int32(sh),
             np.int32(dw), np.int32(dh), np.int32(ch), np.int32(k == 1))
    top_h, top_w = shapes[-1]
    normalise(queue, (top_h * top_w,), None, *levels[-1], np.int32(top_h * top_w),
              np.int32(ch))
    for k in range(len(shapes) - 2, -1, -1):
        lh, lw = shapes[k]
        target = out_buf if k == 0 else levels[k][0]  # in place: a texel reads only itself
        push(queue, (lw, lh), None, *levels[k], levels[k + 1][0], target, np.int32(lw),
             np.int32(lh), np.int32(shapes[k + 1][1]), np.int32(ch), np.int32(k == 0))
    read_output(device, out_buf, out)
    return out[..., 0] if squeeze else out


GUTTER_RING = 2
"""Texels around each chart that take their nearest covered texel's value: a bilinear
lookup inside a chart reads at most one texel beyond it."""


_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
"""Axial neighbours first: a ring texel takes an edge-adjacent chart texel when it has one."""


@lru_cache(maxsize=4)
def _nearest_sources(covered_bytes: bytes, shape: tuple[int, int], ring: int
                     ) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Flat indices of the ring's texels and of the chart texels they copy (one layout's
    coverage, cached: its irradiance, radiance and albedo share them). Grown one texel
    a pass, each new texel taking the source of its first neighbour (in
    :data:`_NEIGHBOURS` order) that has one: memory stays a few bytes a texel (scipy's
    distance transform needed 24). Only a pass's new texels are looked at past the one
    sweep that finds them (eight neighbours' sources over the whole texture took 1.4 s
    a layout at texture 4096)."""
    h, w = shape
    source = np.full(h * w, -1, np.int32)  # a 16384^2 atlas still fits int32
    has = np.frombuffer(covered_bytes, dtype=bool).reshape(h, w).copy()
    source[has.reshape(-1)] = np.flatnonzero(has)
    added: list[NDArray[np.int64]] = []
    for _ in range(ring):
        # the texels without a source beside one with: this pass's new texels, in order
        padded = np.pad(has, 1)
        near = np.zeros_like(has)
        for dy, dx in _NEIGHBOURS:
            near |= padded[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        grown = np.flatnonzero(near & ~has)
        gy, gx = np.divmod(grown, w)
        new = np.full(grown.size, -1, np.int32)
        for dy, dx in _NEIGHBOURS:
            y, x = gy + dy, gx + dx
            inside = (y >= 0) & (y < h) & (x >= 0) & (x < w)
            src = np.where(inside, np.take(source, np.where(inside, y * w + x, 0)), -1)
            take = (new < 0) & (src >= 0)
            new[take] = src[take]
        source[grown] = new
        has.reshape(-1)[grown] = True
        added.append(grown)
    dst_all = np.concatenate(added) if added else np.zeros(0, np.int64)
    return dst_all, source[dst_all].astype(np.int64)


def _gutter(coverage: NDArray[Any], ring: int
            ) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """:func:`_nearest_sources` of ``coverage`` (None where every texel or none is
    covered: no gutter)."""
    covered = np.asarray(coverage) > 0
    if covered.all() or not covered.any():
        return None
    return _nearest_sources(np.ascontiguousarray(covered).tobytes(), covered.shape, ring)


def prepare_dilation(coverage: NDArray[Any], ring: int = GUTTER_RING) -> None:
    """Make what :func:`dilate_charts` reads of ``coverage`` (kept for the layout), say
    on a thread beside other work: at texture 4096 it took 0.2-0.3 s on one core."""
    _gutter(coverage, ring)


def dilate_charts(values: NDArray[Any], coverage: NDArray[Any], ring: int = GUTTER_RING
                  ) -> NDArray[np.float32]:
    """``values`` (H, W[, C]) with each texel within ``ring`` texels of a chart (8-connected
    steps) set to a nearest covered texel's value; in place when ``values`` is float32,
    returned."""
    return _dilated(values, coverage, ring)[0]


def _dilated(values: NDArray[Any], coverage: NDArray[Any], ring: int
             ) -> tuple[NDArray[np.float32], tuple[NDArray[np.int64], NDArray[np.int64]] | None]:
    """:func:`dilate_charts`, and the gutter it copied (None: none)."""
    v = np.asarray(values, dtype=np.float32)
    gutter = _gutter(coverage, ring)
    if gutter is not None:
        dst, src = gutter
        flat = v.reshape(np.size(coverage), -1)
        flat[dst] = flat[src]
    return v, gutter


def extrapolate_charts(values: NDArray[Any], coverage: NDArray[Any], ring: int = GUTTER_RING
                       ) -> NDArray[np.float32]:
    """:func:`dilate_charts`, then each texel next to a chart (8-connected) set to the
    mean of its chart's linear continuations, 2 v(t + d) - v(t + 2 d) over the
    directions d whose two texels are covered (at least 0: light is not negative);
    texels with no such direction keep the copy. In place when ``values`` is float32."""
    v, gutter = _dilated(values, coverage, ring)
    if gutter is None:
        return v
    covered = np.asarray(coverage) > 0
    h, w = covered.shape
    flat = v.reshape(h * w, -1)
    gy, gx = np.divmod(gutter[0], w)
    total = np.zeros((gy.size, flat.shape[1]), np.float64)
    count = np.zeros(gy.size, np.int32)
    for dy, dx in _NEIGHBOURS:
        y1, x1, y2, x2 = gy + dy, gx + dx, gy + 2 * dy, gx + 2 * dx
        ok = (y2 >= 0) & (y2 < h) & (x2 >= 0) & (x2 < w)
        ok[ok] = covered[y1[ok], x1[ok]] & covered[y2[ok], x2[ok]]
        near, far = flat[y1[ok] * w + x1[ok]], flat[y2[ok] * w + x2[ok]]
        total[ok] += 2.0 * near.astype(np.float64) - far
        count[ok] += 1
    some = count > 0
    flat[gutter[0][some]] = np.maximum(total[some] / count[some, None], 0.0)
    return v
