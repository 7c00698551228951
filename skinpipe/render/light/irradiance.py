"""The irradiance entering each texel: shadow rays cast for each light's samples
(interleaved across texel classes, refined adaptively in penumbrae), the interleaved
visibility filtered back to every texel, times the unshadowed irradiance, less what
the specular lobe reflects."""

from __future__ import annotations

import threading
import time
from collections.abc import Collection, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property, lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ...errors import InputError
from ..bands import in_bands
from ..device.choice import Device, or_default
from ..device.memory import (
    host_buffer,
    host_output,
    read_output,
    run_on_host_arrays,
)
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from ..options import INTERLEAVE_PERIODS
from ..scene import Light
from .boundary import SkinBoundary
from .raytrace import (
    OFFSET_FLOAT_SCALE,
    OFFSET_INT_SCALE,
    OFFSET_ORIGIN,
    RayScene,
    morton_order,
)
from .samples import (
    DEVICE_SAMPLED_KINDS,
    LightSampler,
    _sample_kernel,
    light_rng,
    sample_plan,
)

_INTERLEAVE_KERNEL = cl_source(__package__, "interleave.cl")
MAX_FILTER_LIGHTS = 4
"""Lights one filter launch handles (a kernel is built per count, loops unrolled); more
go in further launches."""


@lru_cache(maxsize=4 * MAX_FILTER_LIGHTS)
def _interleave_kernel(device: Device, lights: int, at: bool = False, period: int = 2
                       ) -> Any:
    program = build(device, _INTERLEAVE_KERNEL, [f"-DLIGHTS={lights}", f"-DAT={int(at)}",
                                                 f"-DPERIOD={period}"])
    return Kernel(program, "filter_interleaved", 1 if at else 2)


_PENUMBRA_KERNEL = cl_source(__package__, "penumbra.cl")


@lru_cache(maxsize=len(INTERLEAVE_PERIODS))
def _penumbra_kernel(device: Device, period: int = 2) -> Any:
    return Kernel(build(device, _PENUMBRA_KERNEL, [f"-DPERIOD={period}"]), "penumbra_at", 1)


def irradiance_kernels(device: Device, lights: Sequence[Light], samples: int,
                       interleaved: bool,
                       textured_domes: Collection[str] = (), filtered: bool = True,
                       sequence: str = "stratified", refined: bool = False,
                       period: int = 2) -> list[Any]:
    """The device kernels :func:`irradiance_texture` and (if ``filtered``)
    :func:`filter_interleaved` at the covered texels (``at``, as the renderer runs it)
    or (if ``refined``) :func:`refine_penumbrae`'s :func:`penumbra_at` will launch for
    these lights at the interleaving ``period`` (for :class:`~.opencl.Prewarm`)."""
    kernels, interleaved_lights = [_offset_kernel(device)], 0
    for light in lights:
        if not np.any(light.radiance > 0):
            continue
        count, inter = sample_plan(light, samples, interleaved, sequence, period)
        interleaved_lights += inter
        if light.kind in DEVICE_SAMPLED_KINDS and light.path not in textured_domes:
            kernels.append(_sample_kernel(device, light.kind, count, inter))
            if refined and inter:  # the penumbrae's other classes' strata
                kernels.append(_sample_kernel(device, light.kind,
                                              (period * period - 1) * count, inter))
    if filtered:
        for start in range(0, interleaved_lights, MAX_FILTER_LIGHTS):
            kernels.append(_interleave_kernel(device, min(MAX_FILTER_LIGHTS,
                                                          interleaved_lights - start),
                                              True, period))
    if refined and interleaved_lights:
        kernels.append(_penumbra_kernel(device, period))
    return kernels


def flat_texels(at: NDArray[Any], h: int, w: int) -> NDArray[np.int32]:
    """``at`` as the int32 flat indices of texels of an (h, w) texture the device
    kernels read (a 1-D list, each below h w), or InputError."""
    points = np.asarray(at)
    if points.ndim != 1 or (points.size and (points.min() < 0 or points.max() >= h * w)):
        raise InputError(f"at: flat texel indices below {h * w} expected")
    return points.astype(np.int32, copy=False)


def light_planes(visibility: NDArray[Any], carries: NDArray[np.bool_], texel: NDArray[Any],
                 vis_plane: NDArray[np.float32], traced_plane: NDArray[np.bool_]) -> None:
    """One light's visibility per point and whether its rays could carry any light
    (``carries``: :meth:`IrradianceResult.carries_light`) put into (H, W) planes at the
    points' flat texel indices ``texel`` (by flat index: a boolean mask's scatter took
    2-4x as long at texture 4096)."""
    np.put(vis_plane, texel, visibility)
    np.put(traced_plane, texel, carries)


def visibility_planes(lights: int, shape: tuple[int, int]) -> NDArray[np.float32]:
    """(lights, H, W) planes for :func:`visibility_plane`, every texel untraced (-0.0)."""
    return np.full((lights, *shape), -0.0, np.float32)


def visibility_plane(visibility: NDArray[Any], carries: NDArray[np.bool_],
                     texel: NDArray[Any], plane: NDArray[np.float32]) -> None:
    """One light's visibility per point (>= 0) put into its (H, W) ``plane`` (of
    :func:`visibility_planes`) at the points' flat texel indices ``texel``, as
    :func:`filter_interleaved` reads it without ``traced``: negated (its sign bit set,
    -0.0 for 0) where the point's rays could carry no light (``carries`` false:
    :meth:`IrradianceResult.carries_light`)."""
    np.put(plane, texel, np.where(carries, visibility, np.negative(visibility)))


def filter_interleaved(visibility: NDArray[Any], traced: NDArray[Any] | None,
                       normal: NDArray[Any], min_cos: float = 0.9,
                       at: NDArray[Any] | None = None, period: int = 2,
                       device: Device | None = None) -> NDArray[np.float32]:
    """Texture-space reconstruction of interleaved shadow rays: each texel's visibility
    (L, H, W: one plane per light) becomes the tent average over the (2p - 1)^2 texels
    around it for the ``period`` p, weights (p - |dx|)(p - |dy|) / p^4 ((1 2 1)^2 / 16
    over 3 x 3 at period 2), which weight the p^2 interleaved stratum sets equally
    (Keller & Heidrich 2001). Neighbours count only where ``traced`` > 0 (the texel
    traced rays towards that light) and their normal (H, W, 3) is within acos(min_cos)
    of the texel's, so that a crease or a chart that happens to touch does not bleed.
    OpenCL, one work-item per texel; with ``at`` (flat texel indices, N), only at those
    texels, returned as (L, N) (the renderer's covered texels: the demo face covers 46%
    of its texture). The visibility is a fraction (>= 0); with ``traced`` None, its
    planes say it themselves, negated where a texel traced nothing
    (:func:`visibility_plane`). ``device``: where it runs (None:
    :func:`~..device.choice.or_default`)."""
    vis = np.asarray(visibility, dtype=np.float32)
    if vis.ndim != 3 or (traced is not None and np.shape(traced) != vis.shape) or \
            np.shape(normal) != (*vis.shape[1:], 3):
        raise InputError(f"visibility (L, H, W), traced (L, H, W) and normal (H, W, 3) must "
                         f"agree; got {vis.shape}, {np.shape(traced)}, {np.shape(normal)}")
    if traced is not None:
        if not (vis >= 0).all():
            raise InputError("visibility must be a fraction >= 0 where traced is given; "
                             f"got {float(np.nanmin(vis))}")
        vis = np.where(np.asarray(traced) > 0, vis, np.negative(vis))
    vis = np.ascontiguousarray(vis)
    lights, h, w = vis.shape
    points = None if at is None else flat_texels(at, h, w)
    if points is not None and not points.size:
        return np.zeros((lights, 0), np.float32)
    device = or_default(device)
    # over the arrays' own memory on a CPU device (copies of 0.3 GB took 0.5 s at
    # texture 4096)
    nrm_buf = host_buffer(device, np.asarray(normal, np.float32))
    out = np.empty_like(vis) if points is None else np.empty((lights, points.size),
                                                             np.float32)
    at_args = () if points is None else (host_buffer(device, points), np.int32(points.size))
    for start in range(0, lights, MAX_FILTER_LIGHTS):
        part = slice(start, min(start + MAX_FILTER_LIGHTS, lights))
        out_part = out[part]
        # the buffers (and the arrays they hold) stay referenced until the read
        vis_buf = host_buffer(device, vis[part])
        out_buf = host_output(device, out_part)
        grid = (w, h) if points is None else (points.size,)
        _interleave_kernel(device, part.stop - start, points is not None, period)(
            device.queue, grid, None, vis_buf, nrm_buf, out_buf, np.int32(h),
            np.int32(w), np.float32(min_cos), *at_args)
        read_output(device, out_buf, out_part)
    return out


@dataclass
class IrradianceResult:
    """Irradiance entering the skin per point (``entering``, (N, 3)), and per light the
    fraction of its unshadowed irradiance that arrived (``visibility``, for the specular
    term) and the unshadowed irradiance itself, as weights and a colour, so that
    interleaved visibility can be filtered and applied afterwards (``entering_with``)."""

    arrived: list[tuple[NDArray[np.float32], NDArray[np.float32]]]
    """Per light that adds light, in the lights' order: the weights that reached it per
    point ((N,), or (N, 3) for a textured dome) and its colour (3,): what ``entering``
    sums."""
    visibility: dict[str, NDArray[np.float32]]
    unshadowed: dict[str, tuple[NDArray[np.float32], NDArray[np.float32]]] = \
        field(default_factory=dict)
    """Per light: all its samples' weights per point ((N,), or (N, 3) for a textured
    dome) and its colour (3,), whose product (:func:`coloured`) is its unshadowed
    irradiance (N, 3). Kept apart: the products were 184 MB of new pages and 0.3-0.8 s
    of the main thread beside the rays at texture 4096, and every reader takes a column
    or a test from them."""
    skipped: list[str] = field(default_factory=list)
    rays: int = 0
    seconds: float = 0.0
    interleaved: frozenset[str] = frozenset()
    """Lights whose shadow rays were interleaved (each point traced a share of the
    samples): only their visibility is reconstructed by ``filter_interleaved``."""

    points: int = 0

    @cached_property
    def entering(self) -> NDArray[np.float32]:
        """Irradiance entering the skin per point (N, 3): each light's weights that
        reached it times its colour, summed light by light. Made when first read: an
        interleaved or adaptive render replaces it (``entering_with``), and these sums
        were 1.3 s of its main thread at texture 4096, beside the rays."""
        out = np.zeros((self.points, 3), np.float32)
        for lit, colour in self.arrived:
            if lit.ndim == 1:  # a column at a time, no (N, 3) of products
                for c in range(3):
                    out[:, c] += lit * colour[c]
            else:
                out += lit * colour
        return out

    def entering_with(self, visibility: dict[str, NDArray[Any]]) -> NDArray[np.float32]:
        """Irradiance entering the skin with each light's visibility replaced (e.g. by its
        filtered form): sum of unshadowed x visibility, each unshadowed column made as
        :func:`coloured` makes it (the same products)."""
        out = np.zeros((self.points, 3), np.float32)
        lights = [(weights, colour, np.asarray(visibility[path], np.float32))
                  for path, (weights, colour) in self.unshadowed.items()]

        def band(points: slice) -> None:  # in bands on the cores (0.2 s on one at 4096)
            column = None  # one column's products at a time, reused
            for weights, colour, vis in lights:
                for c in range(3):
                    w = weights[points] if weights.ndim == 1 else weights[points, c]
                    column = np.multiply(w, colour[c], out=column)
                    column *= vis[points]
                    out[points, c] += column

        in_bands(band, self.points)
        return out

    def unshadowed_irradiance(self, path: str) -> NDArray[np.float32]:
        """Light ``path``'s unshadowed irradiance per point (N, 3)."""
        return coloured(*self.unshadowed[path])

    def carries_light(self, path: str) -> NDArray[np.bool_]:
        """Whether light ``path``'s rays could carry any light to each point: its
        unshadowed irradiance summed over the channels > 0. From (N,) weights, without the
        products: ``weights x max(colour) > 0`` is the same test, as the colour is >= 0
        and rounding is monotone (some channel's product is > 0 exactly when the
        largest one is)."""
        weights, colour = self.unshadowed[path]
        if weights.ndim == 1:
            return weights * np.max(colour) > 0
        return sum_axis1(coloured(weights, colour)) > 0


_OFFSET_KERNEL = cl_source(__package__, "offset_origin.cl")


@lru_cache(maxsize=4)
def _offset_kernel(device: Device) -> Any:
    return Kernel(build(device, _OFFSET_KERNEL), "offset_origin", 1)


def ray_origins(points: NDArray[Any], normals: NDArray[Any], device: Device | None = None
                ) -> NDArray[np.float32]:
    """:func:`~.raytrace.offset_ray_origin` on the OpenCL device, the same floats bit for
    bit: the shadow rays' origins (N, 3). numpy's passes took 13 ms of the demo face's
    interleaved irradiance at texture 1024 (0.43 s), before its first ray."""
    p = np.ascontiguousarray(points, dtype=np.float32)
    n = np.ascontiguousarray(normals, dtype=np.float32)
    if n.shape != p.shape or p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points and normals must agree as (N, 3); got {p.shape} and "
                         f"{n.shape}")
    out = np.empty_like(p)
    if p.size:
        device = or_default(device)
        run_on_host_arrays(_offset_kernel(device), device, (p.size,),
                           [p, n, np.float32(OFFSET_INT_SCALE), np.float32(OFFSET_FLOAT_SCALE),
                            np.float32(OFFSET_ORIGIN), np.int32(p.size)], [out])
    return out


def _in_morton_order(pos: NDArray[Any], nrm: NDArray[Any], classes: NDArray[Any] | None
                     ) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any] | None, NDArray[Any]]:
    """Points, normals and classes along a Morton curve, and the order back. Rows are
    gathered by np.take (fancy indexing of (N, 3) rows takes 5x as long) and put back by
    the inverse order's take, not a scatter."""
    order = morton_order(pos)
    back_order = np.empty_like(order)
    back_order[order] = np.arange(order.size)
    return (np.take(pos, order, axis=0), np.take(nrm, order, axis=0),
            None if classes is None else classes[order], back_order)


def irradiance_texture(
    positions: NDArray[Any], normals: NDArray[Any], lights: list[Light], rays: RayScene,
    samples: int = 16, boundary: SkinBoundary | None = None,
    seed: int = 0, dome_textures: dict[str, NDArray[np.float32]] | None = None,
    interleave: NDArray[Any] | None = None, sequence: str = "stratified",
    coherent: bool = False, complement: bool = False, period: int = 2,
    device: Device | None = None,
) -> IrradianceResult:
    """Irradiance entering the skin at surface points (N, 3) with unit normals, summed
    over ``lights`` with ``samples`` shadow rays per light and point (the points of
    :func:`light_sample_set` for ``sequence``; with ``interleave``, a class 0 to p^2 - 1
    per point for the ``period`` p: a p^2-th of them, see ``LightSampler``; the
    per-point visibility is then noisy until ``filter_interleaved`` has run; with
    ``complement`` too, the other classes' strata).

    ``boundary``: what crossing the skin's surface does to the light (the Fresnel share
    each sample loses, per channel the depth factor of its angle; :mod:`.boundary`);
    None: the light enters whole.

    Ray origins are pushed off the surface along the normal by what their floating-point
    error needs (:func:`~.raytrace.offset_ray_origin`); rays whose cosine is <= 0 are
    not cast. The rays go to Embree sorted along a Morton curve of their origins, or in
    the points' own order if they are ``coherent`` (neighbours on the surface next to
    each other, as a texture's texels in :func:`~.texture_maps.texels_in_blocks`). Each
    point's result does not depend on the order. ``device``: where the ray origins and
    samples are made (None: :func:`~..device.choice.or_default`).
    """
    device = or_default(device)
    start = time.perf_counter()
    pos = np.asarray(positions, dtype=np.float32)
    nrm = np.asarray(normals, dtype=np.float32)
    classes = None if interleave is None else np.asarray(interleave)
    back_order = None
    if not coherent:
        pos, nrm, classes, back_order = _in_morton_order(pos, nrm, classes)

    def back(a: NDArray[Any]) -> NDArray[Any]:
        """``a`` (per sorted point) in the points' own order."""
        return a if back_order is None else np.take(a, back_order, axis=0)

    origins = ray_origins(pos, nrm, device)
    arrived: list[tuple[NDArray[np.float32], NDArray[np.float32]]] = []
    visibility: dict[str, NDArray[np.float32]] = {}
    unshadowed_by_light: dict[str, tuple[NDArray[np.float32], NDArray[np.float32]]] = {}
    skipped: list[str] = []
    interleaved: set[str] = set()
    point_buffers: dict[str, Any] = {}  # origins and normals on the device, for every light
    samplers: list[LightSampler] = []
    for light in lights:
        if not np.any(light.radiance > 0):
            skipped.append(f"light {light.path}: zero radiance")
            continue
        samplers.append(LightSampler(light, origins, nrm, samples, light_rng(seed, light),
                                     (dome_textures or {}).get(light.path), classes,
                                     1.0 if boundary is None else boundary.eta,
                                     device=device, point_buffers=point_buffers,
                                     sequence=sequence, complement=complement,
                                     period=period))
    n_rays = 0
    for sampler, lit, unshadowed, cast in cast_samples(samplers, rays):
        light = sampler.light
        n_rays += cast
        if not unshadowed.any():
            skipped.append(f"light {light.path}: adds nothing (all samples below the "
                           "horizon)")
            continue
        if not lit.any():  # its visibility, 0, is still the specular lobe's and the
            # adaptive pass's (which refines a light's penumbrae from it)
            skipped.append(f"light {light.path}: adds nothing (shadowed everywhere)")
        if sampler.sets is not None:
            interleaved.add(light.path)
        visibility[light.path] = back(light_visibility(lit, unshadowed))
        if boundary is not None:  # per channel: the depth its angle enters to
            depth = boundary.depth_factor(incidence_cos(light, pos, nrm))
            lit = (lit if lit.ndim == 2 else lit[:, None]) * depth
            unshadowed = (unshadowed if unshadowed.ndim == 2 else unshadowed[:, None]) * depth
        arrived.append((back(lit), sampler.colour))
        unshadowed_by_light[light.path] = (back(unshadowed), sampler.colour)
    return IrradianceResult(arrived, visibility, unshadowed_by_light, skipped, n_rays,
                            time.perf_counter() - start, frozenset(interleaved), pos.shape[0])


DOME_MEAN_COS = 2.0 / 3.0
"""The mean cosine of a dome's light on a surface (cosine-weighted over the hemisphere)."""


def incidence_cos(light: Light, points: NDArray[Any], normals: NDArray[Any]
                  ) -> NDArray[np.float64]:
    """The cosine at which ``light`` arrives at each point, for the depth factor: its
    centre's direction (a distant, sphere or rect light), a dome's mean."""
    n = np.asarray(normals, dtype=np.float64)
    if light.kind == "dome":
        return np.full(n.shape[0], DOME_MEAN_COS)
    if light.kind == "distant":
        d = np.broadcast_to(-np.asarray(light.axis, np.float64), n.shape)
    else:
        d = np.asarray(light.position, np.float64)[:3] - np.asarray(points, np.float64)
        d = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return np.clip(np.einsum("ij,ij->i", n, d), 0.0, 1.0)


RAY_BLOCK_POINTS = 1 << 21
"""Points whose shadow rays of one sample go to Embree as one job of
:func:`cast_samples` (a sampler on the device; a numpy one's samples go whole): each
worker's rays (16 bytes a point) were a whole sample's, 0.25 GB between the two at
texture 4096, at the irradiance's peak."""


def ray_blocks(sampler: LightSampler) -> list[tuple[int, int]]:
    """(first point, count) of each job of one sample of ``sampler``
    (:data:`RAY_BLOCK_POINTS` at a time on the device; every point at once in numpy)."""
    n = sampler.origins.shape[0]
    if sampler.device is None or n <= RAY_BLOCK_POINTS:
        return [(0, n)]
    return [(s, min(RAY_BLOCK_POINTS, n - s)) for s in range(0, n, RAY_BLOCK_POINTS)]


def cast_samples(samplers: Sequence[LightSampler], rays: RayScene
                 ) -> Iterator[tuple[LightSampler, NDArray[Any], NDArray[Any], int]]:
    """Every sample of every sampler (each over its own points), its shadow rays cast:
    yields per sampler, in turn, (sampler, lit, unshadowed, rays cast), the sums over its
    samples of the weights (entering the skin) that reached the light and of all of
    them, (N,) or (N, 3) for a textured dome. One queue of every sampler's samples on two
    workers: sample k+1's directions are made while sample k's rays are in Embree, and a
    sampler's sums are made (by the caller too) while the next one's rays are: the gaps
    between lights were a tenth of the demo face's interleaved pass at texture 1024,
    and the adaptive pass's lights, one call each, left 60 ms of its 1.1 s idle."""
    worker = threading.local()
    spans = {id(s): ray_blocks(s) for s in samplers}
    most = max((count for s in samplers for _, count in spans[id(s)]), default=0)

    def one(job: tuple[LightSampler, int, tuple[int, int]]) -> tuple[Any, Any, int]:
        # light the specular lobe reflects does not enter the skin; rays of points
        # the sample does not light end where they start (length 0) and are not
        # traced, where gathering the others and scattering their answers back took
        # 25 ms a sample at texture 1024
        sampler, k, (first, n) = job
        if not hasattr(worker, "rays"):
            # each worker's rays from sample to sample in the same arrays (their first
            # rows for fewer points): fresh ones were 0.12 GB of new pages a sample at
            # texture 4096 (zeroed by the kernel)
            worker.rays = (np.empty((most, 3), np.float32), np.empty(most, np.float32))
        d, dist, w = sampler.entering_sample(k, (worker.rays[0][:n], worker.rays[1][:n]),
                                             (first, n))
        cast = int(np.count_nonzero((w if w.ndim == 1 else w.max(axis=1)) > 0))
        if cast == 0:
            return None, None, 0
        open_ = ~rays.occluded(sampler.origins[first:first + n], d, dist)
        # a product, not np.where (2.5 ms a sample on a random mask, 0.3 ms): the
        # weights are finite
        return w * (open_ if w.ndim == 1 else open_[:, None]), w, cast

    jobs = [(sampler, k, span) for sampler in samplers for k in range(sampler.count)
            for span in spans[id(sampler)]]
    pool = ThreadPoolExecutor(2)
    try:
        results = pool.map(one, jobs)
        for i, sampler in enumerate(samplers):
            n = sampler.origins.shape[0]
            lit = np.zeros((n, 3) if sampler.texture is not None else n, np.float32)
            unshadowed = np.zeros_like(lit)
            n_rays = 0
            for first, count in spans[id(sampler)] * sampler.count:  # as the jobs go
                got, full, cast = next(results)
                if got is not None:
                    lit[first:first + count] += got
                    unshadowed[first:first + count] += full
                    n_rays += cast
            sampler.close()
            if i == len(samplers) - 1:
                # the workers end, and their rays' arrays go with them, before the
                # caller's sums of the last light (0.25 GB at texture 4096)
                pool.shutdown(wait=True)
            yield sampler, lit, unshadowed, n_rays
    finally:
        pool.shutdown(wait=True)


def light_visibility(lit: NDArray[Any], unshadowed: NDArray[Any]) -> NDArray[np.float32]:
    """A light's visibility per point from :func:`cast_samples`' sums: the fraction of
    the unshadowed weight that reached it, 0 where none could."""
    lit_s = lit if lit.ndim == 1 else sum_axis1(lit)
    un_s = unshadowed if unshadowed.ndim == 1 else sum_axis1(unshadowed)
    vis = np.where(un_s > 0, lit_s / np.maximum(un_s, 1e-30), 0.0)
    return vis.astype(np.float32, copy=False)


def coloured(weights: NDArray[Any], colour: NDArray[Any]) -> NDArray[np.float32]:
    """A light's unshadowed irradiance (N, 3): its weights ((N,), or (N, 3) for a
    textured dome) times its colour (3,)."""
    return times_colour(weights, colour) if weights.ndim == 1 else weights * colour


def times_colour(values: NDArray[Any], colour: NDArray[Any]) -> NDArray[Any]:
    """``values[:, None] * colour`` (N,) x (3,) -> (N, 3), one column at a time: the same
    products, where numpy's broadcast of (N, 1) against (3,) took 5-6 ms on the demo
    face's 481k texels at texture 1024 (per light, twice, at the end of the irradiance's
    rays) and the columns 0.5 ms."""
    out = np.empty((values.shape[0], 3), np.result_type(values, colour))
    for c in range(3):
        np.multiply(values, colour[c], out=out[:, c])
    return out


def sum_axis1(a: NDArray[Any]) -> NDArray[Any]:
    """``a.sum(axis=1)`` over a short axis 1, its entries added in turn: the same sums
    in the same order, where numpy's reduction over the short axis took 3-6x as long
    (12 against 2-4 ms on the 481k rows of three of the demo face at texture 1024)."""
    out = a[:, 0].copy()
    for k in range(1, a.shape[1]):
        out += a[:, k]
    return out


def penumbra_texels(visibility: NDArray[Any], traced: NDArray[Any],
                    period: int = 2) -> NDArray[np.bool_]:
    """Texels (H, W) whose interleaved shadow rays do not all agree: the texel's own rays
    (visibility strictly between 0 and 1) or those of a traced texel in the (2p - 1)^2
    neighbourhood :func:`filter_interleaved` reads for the ``period`` p (3 x 3 at 2; a
    different visibility). Elsewhere the neighbourhood's rays, all p^2 interleaved sets
    of strata, saw the light all visible or all blocked. The numpy reference of
    :func:`penumbra_at`, which the adaptive pass runs."""
    from scipy.ndimage import maximum_filter, minimum_filter  # lazy, as the fit's solvers

    vis = np.asarray(visibility, np.float32)
    size = 2 * period - 1
    hi = maximum_filter(np.where(traced, vis, 0.0), size=size, mode="constant", cval=0.0)
    lo = minimum_filter(np.where(traced, vis, 1.0), size=size, mode="constant", cval=1.0)
    return traced & ((hi > lo) | ((vis > 0) & (vis < 1)))


def penumbra_at(visibility: NDArray[Any], traced: NDArray[Any],
                at: NDArray[Any], period: int = 2, device: Device | None = None
                ) -> NDArray[np.bool_]:
    """:func:`penumbra_texels` at the texels of ``at`` (flat indices into the (H, W)
    planes), on the OpenCL device: one work-item per listed texel, not two 3 x 3
    filters over the whole texture and a gather (54 ms for the demo face's two lights
    at texture 1024, 46% of whose texels are covered)."""
    vis = np.ascontiguousarray(visibility, np.float32)
    if vis.ndim != 2 or np.shape(traced) != vis.shape:
        raise InputError(f"visibility and traced must be (H, W) planes of one shape; got "
                         f"{vis.shape} and {np.shape(traced)}")
    h, w = vis.shape
    points = flat_texels(at, h, w)
    out = np.zeros(points.size, np.uint8)
    if points.size:
        device = or_default(device)
        run_on_host_arrays(_penumbra_kernel(device, period), device, (points.size,),
                           [vis, np.ascontiguousarray(traced, np.bool_).view(np.uint8),
                            points, np.int32(h), np.int32(w), np.int32(points.size)], [out])
    return out.view(np.bool_)


def _penumbra(result: IrradianceResult, path: str, shape: tuple[int, int],
              texel32: NDArray[Any], period: int, device: Device) -> NDArray[np.int64]:
    """The points (indices of ``result``'s) in a light's penumbra after the interleaved
    pass (:func:`penumbra_at`)."""
    vis1, traced = np.zeros(shape, np.float32), np.zeros(shape, bool)
    light_planes(result.visibility[path], result.carries_light(path), texel32, vis1, traced)
    return np.flatnonzero(penumbra_at(vis1, traced, texel32, period, device))


def _both_passes(result: IrradianceResult, path: str, at: NDArray[np.int64],
                 vis2: NDArray[Any], more_un: NDArray[Any], period: int
                 ) -> tuple[NDArray[Any], tuple[NDArray[Any], NDArray[Any]]]:
    """Light ``path``'s visibility and weights (with its colour) after the adaptive
    pass: at its penumbra points ``at`` the two passes' estimates (the first pass's in
    ``result``; ``vis2``, ``more_un`` the second's) weighted by their strata, elsewhere
    the first pass's. Each pass's weights average over its own strata, 1 / p^2 and the
    rest of them for the ``period`` p: the texel's estimate from all of them weights the
    passes so (0.25 and 0.75 at 2). Weights, not irradiance: the light's colour is in
    both passes' and cancels in the visibility."""
    first = np.float32(1.0 / (period * period))
    rest = np.float32(1.0) - first
    w1, colour = result.unshadowed[path]
    w1_at = np.take(w1, at, axis=0)
    w1_sum = w1_at if w1_at.ndim == 1 else sum_axis1(w1_at)
    w2_sum = more_un if more_un.ndim == 1 else sum_axis1(more_un)
    lit_all = first * result.visibility[path][at] * w1_sum + rest * vis2 * w2_sum
    w_sum = first * w1_sum + rest * w2_sum
    vis = result.visibility[path].copy()
    vis[at] = np.where(w_sum > 0, lit_all / np.maximum(w_sum, 1e-30), 0.0)
    w = w1.copy()
    w[at] = first * w1_at + rest * more_un
    return vis, (w, colour)


def refine_penumbrae(
    result: IrradianceResult, covered: NDArray[np.bool_], positions: NDArray[Any],
    normals: NDArray[Any], interleave: NDArray[Any], lights: list[Light], rays: RayScene,
    samples: int, boundary: SkinBoundary | None = None,
    seed: int = 0, dome_textures: dict[str, NDArray[np.float32]] | None = None,
    sequence: str = "stratified", texel: NDArray[np.intp] | None = None,
    coherent: bool = False, period: int = 2, device: Device | None = None,
) -> tuple[IrradianceResult, dict[str, NDArray[np.int64]]]:
    """Adaptive shadow rays: after an interleaved pass of ``period`` p (``result``: every
    covered texel of ``covered`` traced the p^2-th of the strata its ``interleave``
    class names; the points are the texels at flat indices ``texel``, by default in row
    order), the texels of :func:`penumbra_texels` trace the other classes' strata (the
    same strata: :func:`light_rng`), so that their visibility is their own estimate from
    all ``samples``. Every other texel's neighbourhood agreed, so the interleaved
    reconstruction there is its own value. The error target is full sampling's at a
    fraction of its rays (cast as :func:`irradiance_texture` casts them).
    Returns the result (visibility final, ``interleaved`` empty) and the refined points
    (indices into ``positions``) per light. ``device``: as :func:`irradiance_texture`'s."""
    device = or_default(device)
    start = time.perf_counter()
    visibility = dict(result.visibility)
    unshadowed = dict(result.unshadowed)
    refined: dict[str, NDArray[np.int64]] = {}
    n_rays = result.rays
    classes = np.asarray(interleave)
    pos = np.asarray(positions, dtype=np.float32)
    nrm = np.asarray(normals, dtype=np.float32)
    if texel is None:
        texel = np.flatnonzero(covered)
    texel32 = flat_texels(texel, *covered.shape)  # once for every light's penumbra
    # every light's penumbra first, then all their rays in one queue (cast_samples):
    # one light's sums are merged while the next one's rays are cast
    samplers: list[LightSampler] = []
    cast_at: dict[str, NDArray[np.int64]] = {}
    for light in lights:
        if light.path not in result.interleaved:
            continue
        where = refined[light.path] = _penumbra(result, light.path, covered.shape, texel32,
                                                period, device)
        if not where.size:
            continue
        # each point's result does not depend on the order: the rays go along a
        # Morton curve of the points unless they are coherent already
        at = cast_at[light.path] = where if coherent else where[morton_order(pos[where])]
        nrm_at = np.take(nrm, at, axis=0)  # fancy indexing of (N, 3) rows: 5x as long
        # each penumbra texel the strata of the interleaved classes it has not traced
        # (the other p^2 - 1 shares of them, once each)
        samplers.append(LightSampler(light, ray_origins(np.take(pos, at, axis=0), nrm_at,
                                                        device),
                                     nrm_at, samples, light_rng(seed, light),
                                     (dome_textures or {}).get(light.path), classes[at],
                                     1.0 if boundary is None else boundary.eta,
                                     device=device, sequence=sequence, complement=True,
                                     period=period))
    for sampler, lit, more_un, cast in cast_samples(samplers, rays):
        path, at = sampler.light.path, cast_at[sampler.light.path]
        n_rays += cast
        vis2 = light_visibility(lit, more_un)
        if boundary is not None:  # as the first pass's weights carry it
            more_un = (more_un if more_un.ndim == 2 else more_un[:, None]) * \
                boundary.depth_factor(incidence_cos(sampler.light, pos[at], nrm[at]))
        visibility[path], unshadowed[path] = _both_passes(result, path, at, vis2, more_un,
                                                          period)
    out = replace(result, visibility=visibility, unshadowed=unshadowed, rays=n_rays,
                  seconds=result.seconds + time.perf_counter() - start,
                  interleaved=frozenset())
    out.entering = out.entering_with(visibility)
    return out, refined
