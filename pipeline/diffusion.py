"""Texture-space diffusion: separable Gaussian blurs in OpenCL (PoCL on the CPU).

d'Eon, Luebke, Enderton 2007 (after Borshukov & Lewis 2003): the diffused irradiance is
sum_i w_i (G(v_i) * E), each 2D Gaussian applied as a horizontal then a vertical 1D
pass. The blur is a gather in texture space whose width at each texel comes from the
stretch map (mm per texel along u and v), so the blur is right in mm whatever the UV
layout. Taps outside the chart (coverage 0) are left out and the remaining weights
renormalised, so chart borders neither darken nor leak. Variances are visited in
ascending order and each blur starts from the previous one (G(a) * G(b) = G(a + b)).

The reference implementation in float64 numpy (:func:`blur_reference`) has the same
semantics; the OpenCL kernel must agree with it to 1e-5 relative.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

FloatImage = NDArray[np.float32]
MIN_SIGMA_TEXELS = 0.25
"""Narrower blurs change less than 1e-3 of a texel's energy: the pass is skipped."""
MAX_RADIUS_TEXELS = 512
DIRECT_SIGMA_TEXELS = 2.5
"""Terms narrower than this are blurred from the irradiance itself, not incrementally
from the previous term: a chain of one-texel passes is not Gaussian in shape."""


def _sampled_gaussian_variance(param: NDArray[np.float64]) -> NDArray[np.float64]:
    """Variance (texels^2) of the kernel exp(-k^2 / 2 p^2), |k| <= ceil(3 p), normalised."""
    out = np.empty_like(param)
    for n, p in enumerate(param):
        k = np.arange(-math.ceil(3 * p), math.ceil(3 * p) + 1, dtype=np.float64)
        g = np.exp(-k * k / (2 * p * p))
        out[n] = (k * k * g).sum() / g.sum()
    return out


_PARAM_TABLE = np.linspace(0.3, 1.5, 481)
_VARIANCE_TABLE = _sampled_gaussian_variance(_PARAM_TABLE)


def kernel_parameter(sigma_texels: NDArray[Any]) -> NDArray[np.float32]:
    """The Gaussian parameter whose sampled kernel has variance sigma^2 exactly.

    Below about one texel a sampled Gaussian is narrower than its parameter says (at
    sigma = 0.5 its variance is 0.18, not 0.25), and the error compounds over the
    passes of a profile; above 1.5 texels the two agree to better than 1e-6.
    """
    s = np.asarray(sigma_texels, dtype=np.float64)
    var = s * s
    small = var < _VARIANCE_TABLE[-1]
    out = s.copy()
    out[small] = np.interp(var[small], _VARIANCE_TABLE, _PARAM_TABLE)
    return out.astype(np.float32)

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


@lru_cache(maxsize=1)
def _cl_state() -> tuple[Any, Any, Any]:
    """Context, queue and built program on the first CPU device (PoCL), else any device."""
    import pyopencl as cl

    os.environ.setdefault("POCL_CACHE_DIR", os.path.join(
        os.path.expanduser("~"), ".cache", "skinpipe", "pocl"))
    devices = [d for p in cl.get_platforms() for d in p.get_devices()]
    if not devices:
        raise InputError("no OpenCL device: install pyopencl[pocl] for a CPU device")
    cpu = [d for d in devices if d.type & cl.device_type.CPU]
    ctx = cl.Context([(cpu or devices)[0]])
    queue = cl.CommandQueue(ctx)
    program = cl.Program(ctx, _KERNEL).build(options=[f"-DMIN_SIGMA={MIN_SIGMA_TEXELS}f"])
    return ctx, queue, program


@dataclass
class BlurStats:
    """What the diffusion did: passes run, passes skipped and why."""

    passes: int = 0
    skipped: list[str] = field(default_factory=list)


class OpenCLBlur:
    """Separable 2D Gaussian blurs of an RGBA float32 texture with per-texel sigma.

    Buffers for the stretch-derived sigma maps and coverage live on the device for the
    life of the object, so a sequence of blurs of one texture uploads them once.
    """

    def __init__(self, coverage: NDArray[Any]) -> None:
        import pyopencl as cl

        self.ctx, self.queue, self.program = _cl_state()
        self.kernel = cl.Kernel(self.program, "blur_axis")
        self.height, self.width = coverage.shape
        mf = cl.mem_flags
        cov = np.ascontiguousarray(coverage, dtype=np.float32)
        self.cover_buf = cl.Buffer(self.ctx, mf.READ_ONLY | mf.COPY_HOST_PTR, hostbuf=cov)
        nbytes = self.height * self.width * 16
        self.buf_a = cl.Buffer(self.ctx, mf.READ_WRITE, nbytes)
        self.buf_b = cl.Buffer(self.ctx, mf.READ_WRITE, nbytes)
        self.sigma_u = cl.Buffer(self.ctx, mf.READ_ONLY, self.height * self.width * 4)
        self.sigma_v = cl.Buffer(self.ctx, mf.READ_ONLY, self.height * self.width * 4)

    def upload(self, image: NDArray[Any]) -> None:
        import pyopencl as cl

        rgba = np.ascontiguousarray(image, dtype=np.float32)
        if rgba.shape != (self.height, self.width, 4):
            raise InputError(f"texture must be ({self.height}, {self.width}, 4), got {rgba.shape}")
        cl.enqueue_copy(self.queue, self.buf_a, rgba)

    def download(self) -> FloatImage:
        import pyopencl as cl

        out = np.empty((self.height, self.width, 4), dtype=np.float32)
        cl.enqueue_copy(self.queue, out, self.buf_a)
        return out

    def blur_in_place(self, sigma_u: NDArray[Any], sigma_v: NDArray[Any]) -> None:
        """Blur the device texture by the given per-texel sigmas (texels), u then v."""
        import pyopencl as cl

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

    def blur(self, image: NDArray[Any], sigma_u: NDArray[Any], sigma_v: NDArray[Any]
             ) -> FloatImage:
        self.upload(image)
        self.blur_in_place(sigma_u, sigma_v)
        return self.download()


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
    region-blended ones, so borders between regions blend smoothly. Terms whose weight
    is zero on every texel are skipped, equal variances share a pass, and a term
    narrower than MIN_SIGMA_TEXELS everywhere is folded into the unblurred irradiance.
    """
    e = np.asarray(irradiance, dtype=np.float32)
    h, w, _ = e.shape
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
        rw = None
    else:
        rw = np.asarray(region_weights, dtype=np.float32)
        if rw.shape != (h, w, n_regions):
            raise InputError(f"region weights must be ({h}, {w}, {n_regions}), got {rw.shape}")
    if np.any(np.diff(v) < 0) or np.any(v <= 0):
        raise InputError(f"variances must be > 0 and ascending, got {v.tolist()}")
    stats = BlurStats()
    out = np.zeros((h, w, 3), dtype=np.float32)
    if rw is not None:
        present = rw.reshape(-1, n_regions).max(axis=0) > 0
        for r in np.flatnonzero(~present):
            stats.skipped.append(f"region {r}: no texel uses it")
        used = (tw[present].max(axis=(0, 2)) > 0) if present.any() else np.zeros(v.size, bool)
    else:
        used = tw[0].max(axis=1) > 0
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
                current = blur.download()[..., :3]
                previous_v = v[i]
        elif i > 0:
            stats.skipped.append(f"term {i}: same variance as term {i - 1}, pass shared")
        weight = tw[0, i] if rw is None else rw @ tw[:, i, :]
        out += weight * current
    return out, stats
