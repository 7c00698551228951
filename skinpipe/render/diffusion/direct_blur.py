"""Direct (FIR) separable Gaussian blur in one pass over the texture, for narrow blurs.

A recursive Gaussian (:mod:`.recursive_blur`) costs the same for every sigma, but it
walks the texture twice (a pass along rows written transposed, then again), so it
cannot get under two reads and two writes of the image. For a narrow Gaussian the
direct filter is cheaper: each work item takes a band of B columns down a strip of
rows, filters every input row horizontally into a ring of the last 2R + 1 filtered
rows (in local memory, sized to stay in the L1 cache) and writes each output row as
soon as the ring holds its vertical neighbourhood. The texture is read once and
written once (the ratio of its halo, 2R/B horizontally and 2R/strip vertically,
comes from cache or memory again), and the taps cost about 1.5 ms per unit of radius
at 2048^2 on two cores: the one-pass kernel wins up to radius ~ 16 (sigma ~ 4.3).

Weights are the sampled Gaussian truncated at the smallest radius whose 2D kernel is
within :data:`FIR_MAX_ERROR` of the exact (untruncated) one everywhere, relative to its
peak, renormalised to unit sum; below 1.5 texels the Gaussian's parameter is solved
for the asked variance (a sampled Gaussian narrower than a texel is narrower than
its parameter says), as the gather and recursive blurs do. Texels outside the image
count as zero, as in the recursive blur, so a normalised convolution (RGB times
coverage, coverage in alpha) handles borders. Output rows of textures of
:data:`~.opencl.STREAM_MIN_BYTES` and more are written with streaming stores.
"""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ...errors import InputError
from ..device.choice import Device
from ..device.memory import DeviceTexture, RowBands, in_bands, streams
from ..device.programs import STORE_MACRO, Kernel, build
from ..device.sources import cl_source

FIR_MAX_ERROR = 6e-4
"""Truncation error budget of the direct kernel, relative to the 2D peak (the recursive
blur's own error is 5.5e-4 to 8.5e-4): radius 3 at sigma 1, 7 at sigma 2, 15 at 4."""
FIR_MAX_RADIUS = 16
"""Where the one-sigma direct kernel stopped paying on PoCL (2048^2, two cores: radius
16 costs about what the recursive blur does, 35 ms, and each unit of radius adds about
1.5 ms). The dispatcher uses the switch measured on the device it runs on
(:mod:`.blur_switch`); this value is the one tests pin for device-independent results."""
FIR_MAX_RADIUS_PER_TEXEL = 11
"""Widest per-texel direct kernel built (the tuner's cap; on PoCL also where it stops
paying, :mod:`.blur_switch`): each tap loads the weights of
both texels of a pair (measured at 2048^2 on the demo face's layout: radius 4 18 ms
against 43-45 ms for the per-texel recursive blur, radius 9 34 against 43-47, radius
14 50-64 against 45-51)."""
BUILT_RADII = (2, 4, 7, 11, 16, 24, 32)
"""Radii the direct kernels are built for: a blur runs the smallest at least its own,
its weights padded with zeros (adding zero taps changes no value). A render then
builds a few programs instead of one per radius met (the demo met eight per-texel
radii: on Intel's CPU runtime about 0.8 s a program cold), for a few taps more
(about 1.5 ms a unit of radius at 2048^2)."""
RING_BYTES = 20 * 1024
"""Local-memory ring of 2R + 1 filtered rows of a band: kept inside a 32 KiB L1 cache
(measured at 2048^2, radius 8: 128 KiB ring 68 ms, 17 KiB ring 23.5 ms)."""
MAX_STRIP_ROWS = 256


def truncation_error(sigma: float, radius: int) -> float:
    """Largest |truncated - exact| of the 2D sampled Gaussian, relative to its peak, when
    the 1D kernel is cut at ``radius`` and renormalised (separable: outer products)."""
    half = int(8 * sigma) + radius + 8
    k = np.arange(-half, half + 1, dtype=np.float64)
    g = np.exp(-k * k / (2 * sigma * sigma))
    g /= g.sum()
    t = np.where(np.abs(k) <= radius, g, 0.0)
    t /= t.sum()
    return float(np.abs(np.outer(t, t) - np.outer(g, g)).max() / (g.max() ** 2))


@lru_cache(maxsize=512)
def _radius_for(sigma_key: float, max_error: float) -> int:
    radius = max(1, math.floor(2.5 * sigma_key))
    while truncation_error(sigma_key, radius) > max_error:
        radius += 1
    return radius


def _check_sigma(sigma: float) -> None:
    if not (math.isfinite(sigma) and sigma > 0):
        raise InputError(f"direct blur: sigma must be a positive number of texels, got {sigma}")


def fir_radius(sigma: float, max_error: float = FIR_MAX_ERROR) -> int:
    """Smallest radius (texels) whose truncated kernel is within ``max_error`` of the
    exact Gaussian of ``sigma`` texels (relative to the 2D peak)."""
    _check_sigma(sigma)
    return _radius_for(round(float(sigma), 6), float(max_error))


def sampled_gaussian_variance(param: NDArray[Any], truncate: float) -> NDArray[np.float64]:
    """Variance (texels^2) of the kernel exp(-k^2 / 2 p^2), |k| <= ceil(truncate p),
    normalised, for each parameter p."""
    out = np.empty(np.shape(param))
    for n, p in enumerate(np.asarray(param, np.float64)):
        k = np.arange(-math.ceil(truncate * p), math.ceil(truncate * p) + 1, dtype=np.float64)
        g = np.exp(-k * k / (2 * p * p))
        out[n] = (k * k * g).sum() / g.sum()
    return out


@lru_cache(maxsize=4)
def _parameter_table(truncate: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    params = np.linspace(0.3, 1.5, 481)
    return params, sampled_gaussian_variance(params, truncate)


def kernel_parameter(sigma_texels: NDArray[Any], truncate: float = 3.0) -> NDArray[np.float32]:
    """The Gaussian parameter whose sampled kernel (cut at ``truncate`` parameters: 3 for
    the gather kernel) has variance sigma^2 exactly.

    Below about one texel a sampled Gaussian is narrower than its parameter says (at
    sigma = 0.5 its variance is 0.18, not 0.25), and the error compounds over the
    passes of a profile; above 1.5 texels the two agree to better than 1e-6. Below a
    parameter of 0.3 (a variance of 0.008 texel^2) the parameter stays 0.3.
    """
    params, variances = _parameter_table(float(truncate))
    s = np.asarray(sigma_texels, dtype=np.float64)
    var = s * s
    small = var < variances[-1]
    out = s.copy()
    out[small] = np.interp(var[small], variances, params)
    return out.astype(np.float32)


def fir_parameter(sigma: float) -> float:
    """The parameter of the direct kernel for ``sigma`` texels: :func:`kernel_parameter`
    of the untruncated sampled Gaussian (the direct kernel's own cut is the error
    budget's, not the variance's)."""
    _check_sigma(sigma)
    return float(kernel_parameter(np.array([sigma]), truncate=10.0)[0])


def direct_radius(sigma: float) -> int:
    """Radius of the direct kernel for ``sigma`` texels (that of its parameter)."""
    return fir_radius(fir_parameter(sigma))


def fir_weights(sigma: float) -> NDArray[np.float64]:
    """One-sided weights w[0..R] of the direct kernel for ``sigma`` texels (w[0] + 2
    sum w[1:] = 1): the sampled Gaussian of :func:`fir_parameter`, cut at
    :func:`direct_radius` and renormalised."""
    return fir_weight_table(np.array([sigma], np.float64))[0]


def fir_weight_table(sigma_texels: NDArray[Any]) -> NDArray[np.float64]:
    """(N, R + 1) one-sided weights of the direct kernel, one row per sigma (N,) in
    texels, all cut at the radius of the widest (:func:`direct_radius` of the largest
    sigma): each row is :func:`fir_weights` of its sigma where that radius is its own,
    and a longer (more exact) cut of the same Gaussian otherwise."""
    s = np.atleast_1d(np.asarray(sigma_texels, np.float64))
    for value in (s.min(), s.max()):
        _check_sigma(float(value))
    p = kernel_parameter(s, truncate=10.0).astype(np.float64)[:, None]
    k = np.arange(fir_radius(float(p.max())) + 1, dtype=np.float64)
    w = np.exp(-k * k / (2 * p * p))
    return w / (w[:, :1] + 2 * w[:, 1:].sum(axis=1, keepdims=True))


def built_radius(radius: int) -> int:
    """The :data:`BUILT_RADII` member a blur of ``radius`` runs with."""
    for r in BUILT_RADII:
        if r >= radius:
            return r
    raise InputError(f"direct blur: radius {radius} is wider than {BUILT_RADII[-1]}")


def band_columns(radius_v: int) -> int:
    """Band width B (texels, a power of two in 16..256) whose ring of 2 radius_v + 1
    rows of float4 fits :data:`RING_BYTES`."""
    b = 256
    while b > 16 and (2 * radius_v + 1) * b * 16 > RING_BYTES:
        b //= 2
    return b


def direct_reference(image: NDArray[Any], sigma_u: float, sigma_v: float) -> NDArray[np.float64]:
    """float64 numpy version of the direct blur (u then v, zero outside the image): the
    per-texel reference with one row of weights per axis."""
    rows = np.zeros(np.shape(image)[:2], np.intp)
    return direct_texel_reference(image, fir_weights(sigma_u)[None], fir_weights(sigma_v)[None],
                                  rows, rows)


def direct_texel_reference(image: NDArray[Any], table_u: NDArray[Any], table_v: NDArray[Any],
                           index_u: NDArray[Any], index_v: NDArray[Any]) -> NDArray[np.float64]:
    """float64 numpy version of the per-texel direct blur
    (:meth:`DirectKernels.blur_per_texel`): texel t filtered along u with row
    index_u[t] of ``table_u``, then along v with row index_v[t] of ``table_v``, zero
    outside the image."""
    out = np.asarray(image, np.float64)
    for axis, table, index in ((1, table_u, index_u), (0, table_v, index_v)):
        r = table.shape[1] - 1
        n = out.shape[axis]
        pad = [(0, 0)] * out.ndim
        pad[axis] = (r, r)
        padded = np.pad(out, pad)
        acc = np.zeros_like(out)
        for k in range(-r, r + 1):
            taps = np.take(padded, np.arange(r + k, r + k + n), axis=axis)
            acc += np.asarray(table, np.float64)[index, abs(k)][..., None] * taps
        out = acc
    return out


_HELPERS = cl_source(__package__, "direct_blur_helpers.cl")

_KERNEL = cl_source(__package__, "direct_blur.cl")


def texel_radii_per_program(device: Device, radius: int) -> tuple[int, ...]:
    """The per-texel radii built in one program with ``radius``. Where kernels are
    compiled at their first launch (PoCL), every built radius: its cost to build a
    program is per program (0.29 s cold whatever it holds, measured; about 60 ms from
    its cache), and only the kernels launched are compiled. Elsewhere one radius:
    Intel's CPU runtime compiles every kernel of a program when it builds it (cold:
    8.4 s for all 22 kernels of radii 1-11, against 0.4 s for two), and a render uses
    only a few radii."""
    if device.jit_at_first_launch:
        return tuple(r for r in BUILT_RADII if r <= FIR_MAX_RADIUS_PER_TEXEL)
    return (radius,)


def _texel_source(radii: tuple[int, ...]) -> str:
    """One program with the per-texel kernels of ``radii`` (each the same on both axes)
    for both kinds of store (:func:`texel_radii_per_program`)."""
    parts = [_HELPERS]
    for radius, stream in ((r, s) for r in radii for s in (0, 1)):
        parts += [f"#define RU {radius}\n#define RV {radius}\n#define B {band_columns(radius)}\n"
                  f"#define STREAM {stream}\n#define PER_TEXEL 1\n"
                  f"#define KERNEL_NAME fir_band_texel_{radius}_{stream}\n", STORE_MACRO,
                  _KERNEL, "#undef RU\n#undef RV\n#undef B\n#undef STREAM\n#undef STORE\n"
                  "#undef PER_TEXEL\n#undef KERNEL_NAME\n"]
    return "".join(parts)


class DirectKernels:
    """Built direct-blur kernels: one program per (RU, RV) radius pair for one sigma per
    axis, one per per-texel radius; one per device
    (:func:`direct_kernels`)."""

    def __init__(self, device: Device) -> None:
        self.device = device
        self.ctx, self.queue = device.context, device.queue
        self._kernels: dict[tuple[int, int, bool, bool], Any] = {}
        self._texel_programs: dict[int, Any] = {}

    def kernel(self, ru: int, rv: int, stream: bool, per_texel: bool = False) -> Any:
        key = (ru, rv, stream, per_texel)
        if key not in self._kernels:
            if per_texel:
                if ru != rv or not 1 <= ru <= FIR_MAX_RADIUS_PER_TEXEL:
                    raise InputError(f"per-texel direct blur: radius {ru}, {rv} (one radius "
                                     f"1-{FIR_MAX_RADIUS_PER_TEXEL} for both axes)")
                if ru not in self._texel_programs:
                    radii = texel_radii_per_program(self.device, ru)
                    program = build(self.device, _texel_source(radii))
                    self._texel_programs.update(dict.fromkeys(radii, program))
                self._kernels[key] = Kernel(self._texel_programs[ru],
                                            f"fir_band_texel_{ru}_{int(stream)}", (1, 1))
            else:
                options = [f"-DRU={ru}", f"-DRV={rv}", f"-DB={band_columns(rv)}",
                           f"-DSTREAM={int(stream)}", "-DPER_TEXEL=0", "-DKERNEL_NAME=fir_band"]
                self._kernels[key] = Kernel(build(self.device, STORE_MACRO + _HELPERS
                                                  + _KERNEL, options), "fir_band", (1, 1))
        return self._kernels[key]

    def weights(self, sigma: float) -> tuple[int, Any]:
        """(radius, device buffer of the one-sided float32 weights) for ``sigma`` texels."""
        return _weights_buffer(self.device, round(float(sigma), 6))

    def _run(self, ru: int, rv: int, per_texel: bool, src: Any, dst: Any, height: int,
             width: int, *weights: Any, row_bands: RowBands | None = None) -> None:
        if src is dst:
            raise InputError("direct blur: source and destination must differ")
        b = band_columns(rv)
        bands = -(-width // b)
        # enough work items for every core, without a halo larger than a quarter strip
        strip = min(MAX_STRIP_ROWS, max(8 * rv, -(-height * bands // 64)))
        strips = -(-height // strip)
        stream = streams(height * width * 16)
        kernel = self.kernel(ru, rv, stream, per_texel)
        args = (src, dst, *weights, cl.LocalMemory((2 * rv + 1) * b * 16), np.int32(width),
                np.int32(height), np.int32(strip))
        in_bands(self.queue, row_bands, strips, strip, lambda s0, s1: kernel(
            self.queue, (bands, s1 - s0), (1, 1), *args, global_offset=(0, s0)))

    def blur(self, src: Any, dst: Any, height: int, width: int, sigma_u: float,
             sigma_v: float) -> None:
        """Enqueue one 2D blur of the (height, width) float4 image ``src`` into ``dst``
        (a different buffer: the pass reads its neighbours while it writes)."""
        ru, wu = self.weights(sigma_u)
        rv, wv = self.weights(sigma_v)
        self._run(ru, rv, False, src, dst, height, width, wu, wv)

    def blur_per_texel(self, src: Any, dst: Any, height: int, width: int,
                       table_u: NDArray[Any], table_v: NDArray[Any], index_u: Any,
                       index_v: Any, row_bands: RowBands | None = None) -> None:
        """Enqueue one 2D blur with per-texel weights: texel t uses row index_u[t] of
        ``table_u`` (N, RU + 1) along u and row index_v[t] of ``table_v`` along v (both
        index buffers uint16 in row layout; tables from :func:`fir_weight_table`). The
        tables are padded with zero weights to the :func:`built_radius` of the wider
        one, which both axes then use (at most :data:`FIR_MAX_RADIUS_PER_TEXEL`).
        ``row_bands``: run it a band of rows at a time (:class:`~.opencl.RowBands`)."""
        r = built_radius(max(table_u.shape[1], table_v.shape[1]) - 1)
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        bufs = []
        for t in (table_u, table_v):
            # each weight four times: a float4 load is the broadcast the float4 taps need
            wide = np.zeros((t.shape[0], r + 1, 4), np.float32)
            wide[:, :t.shape[1]] = np.asarray(t, np.float32)[..., None]
            bufs.append(cl.Buffer(self.ctx, flags, hostbuf=wide))
        self._run(r, r, True, src, dst, height, width, *bufs, index_u, index_v,
                  row_bands=row_bands)


@lru_cache(maxsize=256)
def _weights_buffer(device: Device, sigma: float) -> tuple[int, Any]:
    taps = fir_weights(sigma)
    w = np.zeros(built_radius(taps.size - 1) + 1, np.float32)
    w[:taps.size] = taps
    return w.size - 1, cl.Buffer(device.context, cl.mem_flags.READ_ONLY
                                 | cl.mem_flags.COPY_HOST_PTR, hostbuf=w)


@lru_cache(maxsize=4)
def direct_kernels(device: Device) -> DirectKernels:
    return DirectKernels(device)


PREWARMED_TEXEL_RADII = (2, 4, 7)
"""Per-texel radii compiled ahead (:func:`texel_kernels`): those below every measured
switch (8-11); a render that needs 11 compiles it when it first does."""


def texel_kernels(device: Device, stream: bool) -> list[Any]:
    """The per-texel kernels of :data:`PREWARMED_TEXEL_RADII` (for
    :class:`~.opencl.Prewarm`: a render's radii follow its stretch map, not known
    before it)."""
    kernels = direct_kernels(device)
    return [kernels.kernel(r, r, stream, True) for r in PREWARMED_TEXEL_RADII]


class DirectBlur(DeviceTexture):
    """One-pass direct Gaussian blurs of an RGBA float32 texture on the device (one sigma
    per axis, in texels); the same interface as :class:`~.recursive_blur.RecursiveBlur`
    for scalar sigmas."""

    def __init__(self, device: Device, height: int, width: int) -> None:
        super().__init__(device, height, width)
        self.kernels = direct_kernels(device)

    def blur_in_place(self, sigma_u: float, sigma_v: float) -> None:
        """Blur the uploaded texture (the result becomes the texture)."""
        self.kernels.blur(self.buf_a, self.buf_b, self.height, self.width,
                          float(sigma_u), float(sigma_v))
        self.queue.finish()
        self.buf_a, self.buf_b = self.buf_b, self.buf_a
