"""Texture-space diffusion: Gaussian blurs of the irradiance in OpenCL (PoCL on the CPU).

d'Eon, Luebke, Enderton 2007 (after Borshukov & Lewis 2003): the diffused irradiance is
sum_i w_i (G(v_i) * E), each 2D Gaussian applied as a horizontal then a vertical 1D
pass whose width at each texel comes from the stretch map (mm per texel along u and
v), so the blur is right in mm whatever the UV layout.

:func:`diffuse` (the renderer's) blurs every term from the irradiance, as a normalised
convolution of (E coverage, coverage) so chart borders neither darken nor leak: narrow
terms with the one-pass direct kernel of :mod:`.direct_blur` (per-texel weights where
the texel size varies), the others with the recursive Gaussian of
:mod:`.recursive_blur` (cost independent of the width), wide ones on a coarser level of
a pyramid; the blurred terms are then added up a batch at a time, in one pass that
reads the region weights once. :func:`diffuse_gather` is
the first implementation, a per-tap gather whose cost grows with the width, kept for
comparison; :func:`blur_reference` is its float64 reference (1e-5 relative).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ..errors import InputError
from .blur_switch import prefers_direct
from .direct_blur import direct_kernels, fir_weight_table, kernel_parameter
from .opencl import (
    DeviceTexture,
    Kernel,
    build,
    cl_context,
    device_buffer,
    device_cache,
    host_buffer,
    host_output,
    read_output,
)
from .recursive_blur import QUANT_STEPS_PER_OCTAVE, TABLE_MIN_SIGMA, iir_kernels, quantized_log2

FloatImage = NDArray[np.float32]
MIN_SIGMA_TEXELS = 0.25
"""Narrower blurs change less than 1e-3 of a texel's energy: the pass is skipped."""
MAX_RADIUS_TEXELS = 512
DIRECT_SIGMA_TEXELS = 2.5
"""Terms narrower than this are blurred from the irradiance itself, not incrementally
from the previous term: a chain of one-texel passes is not Gaussian in shape."""


_KERNEL = r"""
// One 1D Gaussian pass along `axis` (0 = u/x, 1 = v/y) with a per-texel sigma (texels).
// Every index is clamped to the image before use: PoCL has no bounds checks.
__kernel void blur_axis(__global const float4 *src, __global float4 *dst,
                        __global const float *sigma, __global const float *cover,
                        const int width, const int height, const int axis,
                        const int max_radius)
{
    const int x = get_global_id(0);
    const int y = get_global_id(1);
    if (x >= width || y >= height) return;
    const int i = y * width + x;
    const float s = sigma[i];
    if (!(cover[i] > 0.0f) || !(s >= MIN_SIGMA)) { dst[i] = src[i]; return; }
    const int r = min((int)ceil(3.0f * s), max_radius);
    const float inv2s2 = 0.5f / (s * s);
    float4 acc = (float4)(0.0f);
    float wsum = 0.0f;
    const int lo = axis == 0 ? max(-r, -x) : max(-r, -y);
    const int hi = axis == 0 ? min(r, width - 1 - x) : min(r, height - 1 - y);
    const int step = axis == 0 ? 1 : width;
    for (int k = lo; k <= hi; ++k) {
        const int j = i + k * step;
        const float w = exp(-(float)(k * k) * inv2s2) * cover[j];
        acc += w * src[j];
        wsum += w;
    }
    dst[i] = wsum > 0.0f ? acc / wsum : src[i];
}
"""


def blur_reference(image: NDArray[Any], sigma_u: NDArray[Any], sigma_v: NDArray[Any],
                   coverage: NDArray[Any]) -> NDArray[np.float64]:
    """float64 numpy reference of one 2D blur (u pass, then v pass), same semantics as
    the OpenCL kernel. Slow: for tests and small images."""
    out = np.asarray(image, dtype=np.float64)
    for axis, sigma in ((0, sigma_u), (1, sigma_v)):
        sig = np.asarray(sigma, np.float64)
        param = np.where(sig >= MIN_SIGMA_TEXELS, kernel_parameter(sig).astype(np.float64), sig)
        out = _pass_reference(out, param, np.asarray(coverage, np.float64), axis)
    return out


def _pass_reference(src: NDArray[np.float64], sigma: NDArray[np.float64],
                    cover: NDArray[np.float64], axis: int) -> NDArray[np.float64]:
    h, w = sigma.shape
    dst = src.copy()
    for y in range(h):
        for x in range(w):
            s = sigma[y, x]
            if not cover[y, x] > 0 or not s >= MIN_SIGMA_TEXELS:
                continue
            r = min(math.ceil(3 * s), MAX_RADIUS_TEXELS)
            if axis == 0:
                ks = np.arange(max(-r, -x), min(r, w - 1 - x) + 1)
                taps, cov = src[y, x + ks], cover[y, x + ks]
            else:
                ks = np.arange(max(-r, -y), min(r, h - 1 - y) + 1)
                taps, cov = src[y + ks, x], cover[y + ks, x]
            wts = np.exp(-(ks.astype(np.float64) ** 2) / (2 * s * s)) * cov
            if wts.sum() > 0:
                dst[y, x] = (wts[:, None] * taps).sum(axis=0) / wts.sum()
    return dst


@device_cache()
def _cl_state() -> tuple[Any, Any, Any]:
    """Context, queue and the gather blur's program."""
    ctx, queue = cl_context()
    return ctx, queue, build(_KERNEL, [f"-DMIN_SIGMA={MIN_SIGMA_TEXELS}f"])


@dataclass
class BlurStats:
    """What the diffusion did: passes run, passes skipped and why."""

    passes: int = 0
    """Passes over a texture: two per recursive 2D blur, one per direct one."""
    skipped: list[str] = field(default_factory=list)
    levels: list[int] = field(default_factory=list)
    """Pyramid level each blurred term ran on (0: full resolution)."""
    full_blurs: float = 0.0
    """Texels blurred, in full-resolution 2D blurs."""


class OpenCLBlur(DeviceTexture):
    """Separable 2D Gaussian blurs of an RGBA float32 texture with per-texel sigma.

    Buffers for the stretch-derived sigma maps and coverage live on the device for the
    life of the object, so a sequence of blurs of one texture uploads them once.
    """

    def __init__(self, coverage: NDArray[Any]) -> None:
        super().__init__(*coverage.shape)
        _, _, program = _cl_state()
        self.kernel = Kernel(program, "blur_axis")
        mf = cl.mem_flags
        cov = np.ascontiguousarray(coverage, dtype=np.float32)
        self.cover_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=cov)
        self.sigma_u = cl.Buffer(self.ctx, mf.READ_ONLY, self.height * self.width * 4)
        self.sigma_v = cl.Buffer(self.ctx, mf.READ_ONLY, self.height * self.width * 4)

    def blur_in_place(self, sigma_u: NDArray[Any], sigma_v: NDArray[Any]) -> None:
        """Blur the device texture by the given per-texel sigmas (texels), u then v."""
        for buf, sig in ((self.sigma_u, sigma_u), (self.sigma_v, sigma_v)):
            s = np.asarray(sig, dtype=np.float64)
            param = np.where(s >= MIN_SIGMA_TEXELS, kernel_parameter(s), s)
            cl.enqueue_copy(self.queue, buf, np.ascontiguousarray(param, dtype=np.float32))
        for axis, sig in ((0, self.sigma_u), (1, self.sigma_v)):
            self.kernel(self.queue, (self.width, self.height), None, self.buf_a, self.buf_b,
                        sig, self.cover_buf, np.int32(self.width), np.int32(self.height),
                        np.int32(axis), np.int32(MAX_RADIUS_TEXELS))
            self.buf_a, self.buf_b = self.buf_b, self.buf_a
        self.queue.finish()


def _check_irradiance(irradiance: NDArray[Any]) -> NDArray[np.float32]:
    """(H, W, 3) float32 irradiance, every value finite (else InputError naming a texel)."""
    e = np.asarray(irradiance, dtype=np.float32)
    if e.ndim != 3 or e.shape[2] != 3:
        raise InputError(f"irradiance must be (H, W, 3), got {e.shape}")
    # one float64 sum is finite exactly when every value is (a NaN or inf propagates and
    # float32 values cannot overflow it); the texel is only looked for when it is not
    if not np.isfinite(e.sum(dtype=np.float64)):
        y, x, c = np.argwhere(~np.isfinite(e))[0]
        raise InputError(f"irradiance must be finite; texel ({x}, {y}) channel {c} is {e[y, x, c]}")
    return e


def _region_presence(region_weights: NDArray[np.float32] | None) -> NDArray[np.bool_] | None:
    """Which regions any texel uses (None: one region everywhere)."""
    if region_weights is None:
        return None
    n = region_weights.shape[-1]
    return region_weights.reshape(-1, n).max(axis=0) > 0


def _check_terms(
    shape: tuple[int, int], variances_mm2: NDArray[Any], term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None, present: NDArray[np.bool_] | None,
) -> tuple[NDArray[np.float64], NDArray[np.float32], NDArray[np.bool_], BlurStats]:
    """Checked variances (K,) and term weights (R, K, 3) against a (H, W[, R]) layout,
    which terms any present region uses, and stats noting the regions no texel uses."""
    h, w = shape
    v = np.asarray(variances_mm2, dtype=np.float64)
    tw = np.asarray(term_weights, dtype=np.float32)
    if tw.ndim == 2:
        tw = tw[None]
    n_regions = tw.shape[0]
    if v.ndim != 1 or tw.shape != (n_regions, v.size, 3):
        raise InputError(f"term weights must be (R, K, 3) with K = {v.size}, got {tw.shape}")
    if region_weights is None:
        if n_regions != 1:
            raise InputError(f"{n_regions} regions' weights but no region weight map")
    elif region_weights.shape != (h, w, n_regions):
        raise InputError(f"region weights must be ({h}, {w}, {n_regions}), "
                         f"got {region_weights.shape}")
    if np.any(np.diff(v) < 0) or np.any(v <= 0) or not np.all(np.isfinite(v)):
        raise InputError(f"variances must be finite, > 0 and ascending, got {v.tolist()}")
    stats = BlurStats()
    if present is not None:
        for r in np.flatnonzero(~present):
            stats.skipped.append(f"region {r}: no texel uses it")
        used = (tw[present].max(axis=(0, 2)) > 0) if present.any() else np.zeros(v.size, bool)
    else:
        used = tw[0].max(axis=1) > 0
    return v, tw, used, stats


def _diffusion_inputs(
    irradiance: NDArray[Any], variances_mm2: NDArray[Any], term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None,
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float32],
           NDArray[np.float32] | None, NDArray[np.bool_], BlurStats]:
    """Checked arrays (E, v, term weights (R, K, 3), region weights or None), which
    terms any present region uses, and stats noting the regions no texel uses."""
    e = _check_irradiance(irradiance)
    rw = None if region_weights is None else np.asarray(region_weights, dtype=np.float32)
    v, tw, used, stats = _check_terms(e.shape[:2], variances_mm2, term_weights, rw,
                                      _region_presence(rw))
    return e, v, tw, rw, used, stats


def diffuse_gather(
    irradiance: NDArray[Any],
    mm_per_texel_u: NDArray[Any],
    mm_per_texel_v: NDArray[Any],
    coverage: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None = None,
) -> tuple[NDArray[np.float32], BlurStats]:
    """The first diffusion: the gather kernel, each term blurred from the previous one.

    Same arguments as :func:`diffuse`. Its cost grows with the blur width; it is kept
    as the comparison for the benchmarks and the render report (``--blur gather``), and
    :func:`blur_reference` checks its kernel. Each pass renormalises over the covered
    taps of its own axis (the recursive path normalises in 2D). Equal variances share
    a pass; a term narrower than MIN_SIGMA_TEXELS everywhere is the unblurred irradiance.
    """
    e, v, tw, rw, used, stats = _diffusion_inputs(irradiance, variances_mm2, term_weights,
                                                  region_weights)
    h, w, _ = e.shape
    out = np.zeros((h, w, 3), dtype=np.float32)
    mm_u = np.asarray(mm_per_texel_u, dtype=np.float64)
    mm_v = np.asarray(mm_per_texel_v, dtype=np.float64)
    cov = np.asarray(coverage, dtype=np.float32)
    blur = OpenCLBlur(cov)
    rgba = np.concatenate([e, np.zeros((h, w, 1), np.float32)], axis=2)
    blur.upload(rgba)
    current = e
    previous_v = 0.0
    finest_mm = max(float(np.min(np.where(cov > 0, np.minimum(mm_u, mm_v), np.inf))), 1e-12)
    for i in range(v.size):
        if not used[i]:
            stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): zero weight everywhere")
            continue
        dv = v[i] - previous_v
        if dv > 0:
            if math.sqrt(v[i]) / finest_mm < DIRECT_SIGMA_TEXELS and previous_v > 0:
                blur.upload(rgba)  # start again from the irradiance: see DIRECT_SIGMA
                dv, previous_v = v[i], 0.0
            sig_u = np.sqrt(dv) / np.maximum(mm_u, 1e-12)
            sig_v = np.sqrt(dv) / np.maximum(mm_v, 1e-12)
            if max(sig_u.max(), sig_v.max()) < MIN_SIGMA_TEXELS:
                stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): narrower than a texel, "
                                     "folded into the unblurred irradiance")
                if previous_v == 0.0:
                    current = e  # the device still holds the unblurred irradiance
                else:
                    previous_v = v[i]  # within a quarter texel of the last blur
            else:
                blur.blur_in_place(sig_u, sig_v)
                stats.passes += 2
                stats.full_blurs += 1.0
                current = blur.download()[..., :3]
                previous_v = v[i]
        elif i > 0:
            stats.skipped.append(f"term {i}: same variance as term {i - 1}, pass shared")
        weight = tw[0, i] if rw is None else rw @ tw[:, i, :]
        out += weight * current
    return out, stats


# ----------------------------------------------------------- recursive, on a pyramid

LEVEL_MIN_SIGMA_TEXELS = 4.0
"""A term is blurred on the coarsest pyramid level where its narrowest blur is still
this many of that level's texels: bilinear reads of a Gaussian that wide are within
about h^2 |G''| / 8 = 1 / (8 * 16) of its peak, and each level down quarters the work."""
MAX_LEVELS = 6

_PYRAMID_KERNEL = r"""
// Coarser level: weights (1, 3, 3, 1) / 8 over finer texels 2x-1 .. 2x+2 on each axis,
// so a texel's mass lands around its own position (a 2x2 box would move it by up to
// half a texel). Texels outside the finer image count as zero (no coverage); the 1/8
// an edge texel would give to a coarse texel outside goes to the edge one instead,
// so every finer texel hands on exactly its mass.
__kernel void downsample_tent(__global const float4 *src, __global float4 *dst,
                              const int sw, const int sh, const int dw, const int dh)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= dw || y >= dh) return;
    if (x > 0 && y > 0 && x < dw - 1 && y < dh - 1 && 2 * x + 2 < sw && 2 * y + 2 < sh) {
        // interior: every tap inside and no edge weights to adjust (no branches)
        float4 rows[4];
        for (int j = 0; j < 4; ++j) {
            __global const float4 *r = src + (size_t)(2 * y + j - 1) * sw + 2 * x - 1;
            rows[j] = 0.125f * (r[0] + r[3]) + 0.375f * (r[1] + r[2]);
        }
        dst[y * dw + x] = 0.125f * (rows[0] + rows[3]) + 0.375f * (rows[1] + rows[2]);
        return;
    }
    float wx[4] = {0.125f, 0.375f, 0.375f, 0.125f};
    float wy[4] = {0.125f, 0.375f, 0.375f, 0.125f};
    if (x == 0) wx[1] += 0.125f;
    if (x == dw - 1 && sw == 2 * dw) wx[2] += 0.125f;
    if (y == 0) wy[1] += 0.125f;
    if (y == dh - 1 && sh == 2 * dh) wy[2] += 0.125f;
    float4 acc = 0.0f;
    for (int j = 0; j < 4; ++j) {
        const int sy = 2 * y + j - 1;
        if (sy < 0 || sy >= sh) continue;
        for (int i = 0; i < 4; ++i) {
            const int sx = 2 * x + i - 1;
            if (sx >= 0 && sx < sw) acc += (wx[i] * wy[j]) * src[sy * sw + sx];
        }
    }
    dst[y * dw + x] = acc;
}

// One batch of blurred terms added up at each texel, each (sum_r rw[r] tw[job, r]) times
// rgb / alpha of its blurred (E cov, cov) texture (normalised convolution: texels off
// the charts give nothing and take nothing), read at this texel or bilinearly from a
// pyramid level 2^-level as large. Job n of the batch: jobs[5n .. 5n+4] = (offset of its
// texture in `terms` in float4; job index into tw; level width; level height; its
// level, -1 for the unblurred irradiance `base`). The region weights are read once for
// the whole batch (a pass per term read them, 24 bytes a texel with six regions, once
// per term). The sum goes to `rgb` (the result's own memory on a CPU device); acc_in:
// added to what the previous batches left there.
#define INL __attribute__((always_inline)) inline
// Plain comparisons, not clamp/min: PoCL leaves those builtins as calls, which keep it
// from vectorising the work items (measured: one bilinear term 47-53 ms at 2048^2 with
// them).
INL float4 bilinear(__global const float4 *level, int x, int y, int lw, int lh, float scale)
{
    float fx = ((float)x + 0.5f) * scale - 0.5f, fy = ((float)y + 0.5f) * scale - 0.5f;
    fx = fx < 0.0f ? 0.0f : fx;
    fy = fy < 0.0f ? 0.0f : fy;
    int x0 = (int)fx, y0 = (int)fy;
    x0 = x0 > lw - 2 ? lw - 2 : x0;
    y0 = y0 > lh - 2 ? lh - 2 : y0;
    x0 = x0 < 0 ? 0 : x0;
    y0 = y0 < 0 ? 0 : y0;
    const int x1 = x0 + 1 < lw ? x0 + 1 : lw - 1, y1 = y0 + 1 < lh ? y0 + 1 : lh - 1;
    float ax = fx - (float)x0, ay = fy - (float)y0;
    ax = ax > 1.0f ? 1.0f : ax;
    ay = ay > 1.0f ? 1.0f : ay;
    __global const float4 *r0 = level + y0 * lw, *r1 = level + y1 * lw;
    return (1.0f - ay) * ((1.0f - ax) * r0[x0] + ax * r0[x1])
        + ay * ((1.0f - ax) * r1[x0] + ax * r1[x1]);
}
__kernel void accumulate_terms(__global const float4 *terms, __global const float4 *base,
                               __constant int *jobs, __global float *rgb,
                               __global const float *cover, __global const float *rw,
                               __constant float4 *tw, const int w, const int h,
                               const int n_jobs, const int acc_in)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= w || y >= h) return;
    const int i = y * w + x;
    // every work item takes the same branches (the jobs are uniform): no divergence
    float4 sum = acc_in ? (float4)(rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2], 0.0f)
                        : (float4)(0.0f);
#if REGIONS > 0
    float r[REGIONS];
#pragma unroll
    for (int k = 0; k < REGIONS; ++k) r[k] = rw[(size_t)i * REGIONS + k];
#endif
    for (int n = 0; n < n_jobs; ++n) {
        const int off = jobs[5 * n], job = jobs[5 * n + 1], level = jobs[5 * n + 4];
        float4 t;
        if (level < 0) t = base[i];
        else if (level == 0) t = terms[(size_t)off + i];
        else t = bilinear(terms + off, x, y, jobs[5 * n + 2], jobs[5 * n + 3],
                          1.0f / (float)(1 << level));
#if REGIONS > 0
        float4 wgt = 0.0f;
#pragma unroll
        for (int k = 0; k < REGIONS; ++k) wgt += r[k] * tw[job * REGIONS + k];
#else
        const float4 wgt = tw[job];
#endif
        sum += (t.w > 1e-7f ? 1.0f / t.w : 0.0f) * wgt * t;
    }
    sum = cover[i] > 0.0f ? sum : (float4)(0.0f);
    rgb[3 * i] = sum.x; rgb[3 * i + 1] = sum.y; rgb[3 * i + 2] = sum.z;
}
"""


@device_cache(maxsize=8)
def pyramid_kernels(regions: int) -> dict[str, Any]:
    """The pack, downsample and accumulation kernels for ``regions`` region weights a
    texel (0: one region), in one program. The accumulation's jobs (their pyramid
    levels, whether to add to the output) are arguments, not compiled in: a program a
    batch cost a cold render a PoCL build (0.3 s) and a compilation of each kernel per
    batch, for no measurable gain in the accumulation itself."""

    program = build(_PACK_KERNEL + _PYRAMID_KERNEL, [f"-DREGIONS={regions}"])
    return {name: Kernel(program, name, dims)
            for name, dims in (("pack_coverage", 1), ("downsample_tent", 2),
                               ("accumulate_terms", 2))}


def _added_variance_texels2(level: int) -> float:
    """Variance (finest texels^2, per axis) that reaching pyramid ``level`` and reading
    it back adds: each (1, 3, 3, 1) / 8 step down 3/4 of its finer texel^2, the bilinear
    read at the finest texels' centres t (1 - t) 4^level averaged over their phases t."""
    if level == 0:
        return 0.0
    n = 4.0**level
    return (n - 1.0) / 4.0 + n / 6.0 + 1.0 / 12.0


def _box_down(a: NDArray[np.float32]) -> NDArray[np.float32]:
    """Mean over 2x2 blocks (an odd last row/column averages with itself)."""
    h, w = a.shape
    p = np.pad(a, ((0, h % 2), (0, w % 2)), mode="edge")
    return 0.25 * (p[0::2, 0::2] + p[1::2, 0::2] + p[0::2, 1::2] + p[1::2, 1::2])


def _level_shapes(h: int, w: int) -> list[tuple[int, int]]:
    """(height, width) of each pyramid level, halving (rounded up) while 8 texels remain."""
    shapes = [(h, w)]
    while len(shapes) < MAX_LEVELS and min(h, w) >> len(shapes) >= 8:
        shapes.append(((shapes[-1][0] + 1) // 2, (shapes[-1][1] + 1) // 2))
    return shapes


_PACK_KERNEL = r"""
// (E cov, cov): the normalised convolution's input, from RGB irradiance and coverage
__kernel void pack_coverage(__global const float *rgb, __global const float *cover,
                            __global float4 *dst, const int texels)
{
    const int i = get_global_id(0);
    if (i >= texels) return;
    const float c = cover[i];
    dst[i] = (float4)(c * rgb[3 * i], c * rgb[3 * i + 1], c * rgb[3 * i + 2], c);
}
"""


DIRECT_TEXEL_QUANTILE = 1e-4
"""The per-texel direct blur's radius is set by the texel sizes from this quantile up:
one in 10^4 texels can be far smaller than the rest (degenerate UV, on the demo face
ten at 0.011 mm against 0.082 mm at this quantile and 0.105 mm median), and they
would set a radius far wider than every other texel needs; they are blurred as if
they were the quantile's size (narrower than their own sigma), and counted."""
TERM_BUFFER_TEXTURES = 4
"""Blurred terms kept at once before they are added up, in full-resolution textures
(64 MiB each at 2048^2): each further batch reads and writes the result once more."""
_TERM_ALIGN = 4096
"""Byte alignment of each term in the term buffer (a sub-buffer's origin must be aligned
to the device's base address alignment, at most 4 KiB)."""


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


class DiffusionLayout:
    """What the diffusion of one texture layout needs besides the irradiance, on the
    device: coverage, region weights, the pyramid's shapes, each level's per-texel
    coefficient indices (texel size on a log2 grid, :func:`~.recursive_blur.quantized_log2`).
    It depends on the UV layout and the texture size only, so a renderer makes it once
    and reuses it for every frame and light (:func:`diffuse_prepared`), and it keeps the
    work buffers: first touching fresh device memory costs PoCL about as much as a blur.
    """

    def __init__(self, mm_per_texel_u: NDArray[Any], mm_per_texel_v: NDArray[Any],
                 coverage: NDArray[Any], region_weights: NDArray[Any] | None = None) -> None:
        cov = np.asarray(coverage, dtype=np.float32)
        if cov.ndim != 2:
            raise InputError(f"coverage must be (H, W), got {cov.shape}")
        h, w = cov.shape
        mm = [np.asarray(m, dtype=np.float32) for m in (mm_per_texel_u, mm_per_texel_v)]
        if any(m.shape != (h, w) for m in mm):
            raise InputError(f"coverage and mm-per-texel maps must be ({h}, {w})")
        self.height, self.width = h, w
        self.region_weights = None if region_weights is None else \
            np.asarray(region_weights, dtype=np.float32)
        if self.region_weights is not None and (self.region_weights.ndim != 3
                                                or self.region_weights.shape[:2] != (h, w)):
            raise InputError(f"region weights must be ({h}, {w}, R), "
                             f"got {self.region_weights.shape}")
        self.present = _region_presence(self.region_weights)
        covered = cov > 0
        self.any_covered = bool(covered.any())
        self.shapes = _level_shapes(h, w)
        self._index: dict[int, tuple[int, int, int, int, Any, Any]] = {}
        self._texel_index: dict[int, TexelSteps | None] = {}
        self._steps: dict[int, tuple[NDArray[np.int32], ...]] = {}
        self._buffers: dict[str, Any] = {}
        if not self.any_covered:
            return
        on_chart = [m[covered] for m in mm]
        for name, m, mc in zip("uv", mm, on_chart, strict=True):
            if not (np.isfinite(mc).all() and mc.min() > 0):
                y, x = np.argwhere(covered & ~(np.isfinite(m) & (m > 0)))[0]
                raise InputError(f"mm per texel ({name}) must be finite and > 0 on covered "
                                 f"texels; texel ({x}, {y}) has {m[y, x]}")
        self.typical = [float(np.median(mc)) for mc in on_chart]
        self.uniform = all(float(mc.max() - mc.min()) <= 1e-6 * float(mc.max())
                           for mc in on_chart)
        # the level is chosen for the narrowest blur but for the 1% smallest texels
        self.coarse_mm = max(float(np.percentile(mc, 99.0)) for mc in on_chart)
        self.finest_mm = min(float(mc.min()) for mc in on_chart)
        del on_chart
        # texels off the charts carry nothing, but the recursion runs through them: give
        # them a typical size so their coefficients stay in range
        self._mm = [np.where(covered, m, np.float32(t))
                    for m, t in zip(mm, self.typical, strict=True)]
        self.iir = iir_kernels()
        self.cover_buf = host_buffer(cov)
        self.n_regions = 0 if self.region_weights is None else self.region_weights.shape[2]
        self.rw_buf = host_buffer(self.region_weights if self.region_weights is not None
                                  else np.zeros(1, np.float32))

    def _level_steps(self, k: int) -> tuple[NDArray[np.int32], NDArray[np.int32]]:
        """Level ``k``'s texel sizes (u, v) on the log2 grid, in finest texels (a
        level-k texel's size is the mean of the finer texels it covers)."""
        if k not in self._steps:  # kept until both kinds of index are made from them
            mm_k = self._mm
            for _ in range(k):
                mm_k = [_box_down(m) for m in mm_k]
            self._steps[k] = tuple(quantized_log2(m * np.float32(2.0**k)) for m in mm_k)
        return self._steps[k]

    def level_index(self, k: int) -> tuple[int, int, int, int, Any, Any]:
        """(lowest u step, highest u step, lowest v step, highest v step, u index buffer
        (int32, row layout), v index buffer (transposed)) of level ``k``'s texel sizes
        on the log2 grid, for the recursive blur; made on first use."""
        if k not in self._index:
            qu, qv = self._level_steps(k)
            flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
            lo_u, lo_v = int(qu.min()), int(qv.min())
            self._index[k] = (
                lo_u, int(qu.max()), lo_v, int(qv.max()),
                cl.Buffer(self.iir.ctx, flags, hostbuf=(qu - lo_u).astype(np.int32)),
                cl.Buffer(self.iir.ctx, flags,
                          hostbuf=np.ascontiguousarray((qv - lo_v).T, np.int32)))
            self._release_steps(k)
        return self._index[k]

    def _release_steps(self, k: int) -> None:
        """Drop level ``k``'s texel-size steps once both kinds of index are made."""
        if k in self._index and k in self._texel_index:
            self._steps.pop(k, None)

    def texel_steps(self, k: int) -> TexelSteps | None:
        """Level ``k``'s :class:`TexelSteps` for the per-texel direct blur, made on first
        use; None when the steps span more than a uint16 holds."""
        if k not in self._texel_index:
            qu, qv = self._level_steps(k)
            steps, indices, smaller = [], [], 0
            for q in (qu, qv):
                lo = int(np.floor(np.quantile(q, DIRECT_TEXEL_QUANTILE)))
                steps.append(np.arange(lo, int(q.max()) + 1, dtype=np.int32))
                smaller += int((q < lo).sum())
                indices.append(np.maximum(q - lo, 0))
            if max(st.size for st in steps) > 65535:
                self._texel_index[k] = None
            else:
                flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
                self._texel_index[k] = TexelSteps(
                    *steps, *(cl.Buffer(self.iir.ctx, flags, hostbuf=i.astype(np.uint16))
                              for i in indices), smaller)
            self._release_steps(k)
        return self._texel_index[k]

    def buffer(self, name: str, nbytes: int) -> Any:
        """A device work buffer of at least ``nbytes``, kept for the next diffusion of
        this layout."""
        if name not in self._buffers or self._buffers[name].size < nbytes:
            self._buffers.pop(name, None)  # its memory goes before the larger one comes
            self._buffers[name] = device_buffer(nbytes)
        return self._buffers[name]


def _term_batches(sizes: list[int], budget: int) -> list[dict[int, tuple[int, int]]]:
    """Consecutive jobs grouped so that each group's blurred textures (``sizes`` bytes,
    0 for one that reads the irradiance itself) fit ``budget`` bytes side by side: per
    group, job -> (start, end) byte range in the term buffer."""
    batches: list[dict[int, tuple[int, int]]] = [{}]
    used = 0
    for j, size in enumerate(sizes):
        span = -(-size // _TERM_ALIGN) * _TERM_ALIGN
        if batches[-1] and used + span > budget:
            batches.append({})
            used = 0
        batches[-1][j] = (used, used + max(size, 16))
        used += span
    return batches


def _blur_job(layout: DiffusionLayout, src: Any, tmp: Any, dst: Any, variance: float,
              k: int, stats: BlurStats) -> None:
    """Enqueue the blur of one term (``variance`` mm^2) of pyramid level ``k`` (``src``)
    into ``dst``: sigma per axis less what the pyramid and its bilinear read add; the
    direct kernel for narrow uniform blurs, else the recursive one (per texel where
    the layout's texel sizes vary)."""
    iir = layout.iir
    lh, lw = layout.shapes[k]
    sigma_mm = [math.sqrt(max(variance - (_added_variance_texels2(k) * t**2 if k else 0.0),
                              1e-30)) for t in layout.typical]
    if layout.uniform:
        su, sv = (sg / (t * 2.0**k) for sg, t in zip(sigma_mm, layout.typical, strict=True))
        if prefers_direct(su, sv):  # narrow: one pass of the direct kernel is cheaper
            direct_kernels().blur(src, dst, lh, lw, su, sv)
            stats.passes += 1
            return
        iir.blur(src, tmp, dst, lh, lw, iir.coefficients(su), iir.coefficients(sv))
    else:
        steps = layout.texel_steps(k)
        if steps is not None:
            # per-texel sigma (level texels) on each axis's log2 grid; the widest at its
            # smallest texel sets the radius
            sigmas = [sg / 2.0 ** (q / QUANT_STEPS_PER_OCTAVE)
                      for sg, q in zip(sigma_mm, (steps.u, steps.v), strict=True)]
            if prefers_direct(float(sigmas[0][0]), float(sigmas[1][0]), per_texel=True):
                direct_kernels().blur_per_texel(src, dst, lh, lw, fir_weight_table(sigmas[0]),
                                                fir_weight_table(sigmas[1]), steps.index_u,
                                                steps.index_v)
                stats.passes += 1
                note = (f"level {k}: {steps.smaller} texel sizes below the "
                        f"{DIRECT_TEXEL_QUANTILE:g} quantile blurred as that size")
                if steps.smaller and note not in stats.skipped:
                    stats.skipped.append(note)
                return
        lo_u, hi_u, lo_v, hi_v, index_u, index_v = layout.level_index(k)
        coefs = [iir.coefficients(sg / 2.0 ** (np.arange(lo, hi + 1) / QUANT_STEPS_PER_OCTAVE))
                 for sg, lo, hi in ((sigma_mm[0], lo_u, hi_u), (sigma_mm[1], lo_v, hi_v))]
        iir.blur(src, tmp, dst, lh, lw, coefs[0], coefs[1], index_u, index_v)
    stats.passes += 2


def diffuse(
    irradiance: NDArray[Any],
    mm_per_texel_u: NDArray[Any],
    mm_per_texel_v: NDArray[Any],
    coverage: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None = None,
) -> tuple[NDArray[np.float32], BlurStats]:
    """Diffused irradiance sum_i w_i(texel) (G(v_i) * E) for RGB irradiance (H, W, 3).

    ``variances_mm2`` (K,) ascending, shared by all regions; ``term_weights`` (R, K, 3)
    each region's weight per term and channel; ``region_weights`` (H, W, R) how much of
    each region a texel is (None: one region everywhere). A texel's weights are the
    region-blended ones, so borders between regions blend smoothly. The layout is made
    for this call; :class:`DiffusionLayout` and :func:`diffuse_prepared` keep it.
    """
    layout = DiffusionLayout(mm_per_texel_u, mm_per_texel_v, coverage, region_weights)
    return diffuse_prepared(layout, irradiance, variances_mm2, term_weights)


def diffuse_prepared(
    layout: DiffusionLayout,
    irradiance: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
) -> tuple[NDArray[np.float32], BlurStats]:
    """:func:`diffuse` on a prepared layout.

    Each term is blurred from the irradiance (:func:`_blur_job`: the direct kernel when
    narrow, else the recursive one), with per-texel sigma from the stretch maps, as a
    normalised convolution of (E cov, cov) (chart borders neither darken nor leak), on
    the coarsest level of a (1, 3, 3, 1) pyramid where it is still
    LEVEL_MIN_SIGMA_TEXELS wide (the variance the pyramid and bilinear read add is
    taken off the blur). The blurred terms are kept TERM_BUFFER_TEXTURES at a time and
    added up in one pass per batch. On a CPU device the irradiance is read and the
    result written where they are, in host memory. Terms with zero weight on every
    texel are skipped; one narrower than a quarter texel everywhere is the unblurred
    irradiance.
    """
    h, w = layout.height, layout.width
    e = _check_irradiance(irradiance)
    if e.shape[:2] != (h, w):
        raise InputError(f"irradiance must be ({h}, {w}, 3) like its layout, got {e.shape}")
    v, tw, used, stats = _check_terms((h, w), variances_mm2, term_weights,
                                      layout.region_weights, layout.present)
    if not layout.any_covered or not used.any():
        if not layout.any_covered:
            stats.skipped.append("diffusion: no covered texel")
        return np.zeros((h, w, 3), np.float32), stats
    iir = layout.iir
    queue = iir.queue
    shapes = layout.shapes
    n_levels = len(shapes)

    def term_level(variance: float) -> int:
        sigma = math.sqrt(variance) / layout.coarse_mm  # narrowest blur, finest texels
        k = 0
        while k + 1 < n_levels and sigma / 2 ** (k + 1) >= LEVEL_MIN_SIGMA_TEXELS:
            k += 1
        return k

    # one job per distinct (variance, level): equal variances share a blur, and their
    # weights add (accumulation is linear in them); sub-texel terms share the unblurred
    # irradiance (variance 0)
    jobs: list[tuple[float, int]] = []
    job_weights: list[NDArray[np.float32]] = []
    for i in range(v.size):
        if not used[i]:
            stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): zero weight everywhere")
            continue
        job = (float(v[i]), term_level(float(v[i])))
        if math.sqrt(v[i]) / layout.finest_mm < TABLE_MIN_SIGMA:
            stats.skipped.append(f"term {i} (v = {v[i]:.4g} mm^2): narrower than a quarter "
                                 "texel, the unblurred irradiance")
            job = (0.0, 0)
        if job in jobs:
            if job[0] > 0:
                stats.skipped.append(f"term {i}: same variance as term {i - 1}, pass shared")
            job_weights[jobs.index(job)] += tw[:, i]
        else:
            jobs.append(job)
            job_weights.append(tw[:, i].copy())
    need = max(k for _, k in jobs)
    nbytes = h * w * 16
    mf = cl.mem_flags
    tmp = layout.buffer("tmp", nbytes)
    pyramid = [layout.buffer("level0", nbytes)]
    batches = _term_batches([0 if var == 0.0 else shapes[k][0] * shapes[k][1] * 16
                             for var, k in jobs], TERM_BUFFER_TEXTURES * nbytes)
    kernels = pyramid_kernels(layout.n_regions)
    source = host_buffer(e)  # RGB: 12 of its 16 bytes a texel, read where it is
    kernels["pack_coverage"](queue, (h * w,), None, source, layout.cover_buf,
                                 pyramid[0], np.int32(h * w))
    for k in range(1, need + 1):
        (sh, sw), (dh, dw) = shapes[k - 1], shapes[k]
        pyramid.append(layout.buffer(f"level{k}", dh * dw * 16))
        kernels["downsample_tent"](queue, (dw, dh), None, pyramid[k - 1], pyramid[k],
                                       np.int32(sw), np.int32(sh), np.int32(dw), np.int32(dh))
    tw4 = np.zeros((len(jobs), tw.shape[0], 4), np.float32)
    tw4[..., :3] = np.stack(job_weights)
    tw_buf = cl.Buffer(iir.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=tw4)
    terms = layout.buffer("terms", max(end for batch in batches for _, end in batch.values()))
    out = np.empty((h, w, 3), np.float32)
    out_buf = host_output(out)  # every batch adds its terms there

    blurred_texels = 0.0
    for b, batch in enumerate(batches):
        table = np.zeros((len(batch), 5), np.int32)
        for n, (j, (start, end)) in enumerate(batch.items()):
            variance, k = jobs[j]
            lh, lw = shapes[k]
            table[n] = (start // 16, j, lw, lh, k if variance > 0 else -1)
            if variance == 0.0:
                continue
            work = terms.get_sub_region(start, end - start)
            _blur_job(layout, pyramid[k], tmp, work, variance, k, stats)
            stats.levels.append(k)
            blurred_texels += lh * lw
        kernels["accumulate_terms"](
            queue, (w, h), None, terms, pyramid[0],
            cl.Buffer(iir.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=table.reshape(-1)),
            out_buf, layout.cover_buf, layout.rw_buf, tw_buf, np.int32(w), np.int32(h),
            np.int32(len(batch)), np.int32(b > 0))
    read_output(queue, out_buf, out)
    stats.full_blurs = blurred_texels / (h * w)
    return out, stats
