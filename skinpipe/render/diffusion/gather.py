"""The first diffusion, kept as a reference: each term a per-tap gather of the
irradiance over the full texture (``--blur gather``), and a numpy reference of the
per-texel Gaussian pass that the tests hold the OpenCL kernels to."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ..device.choice import Device, or_default
from ..device.memory import (
    DeviceTexture,
)
from ..device.programs import Kernel, build
from ..device.sources import cl_source
from .direct_blur import kernel_parameter
from .inputs import (
    BlurStats,
    _check_irradiance,
    _check_terms,
    _region_presence,
    unit_region_weights,
)

MIN_SIGMA_TEXELS = 0.25
"""Narrower blurs change less than 1e-3 of a texel's energy: the pass is skipped."""
MAX_RADIUS_TEXELS = 512
DIRECT_SIGMA_TEXELS = 2.5
"""Terms narrower than this are blurred from the irradiance itself, not incrementally
from the previous term: a chain of one-texel passes is not Gaussian in shape."""


_KERNEL = cl_source(__package__, "gather.cl")


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


def _gather_program(device: Device) -> Any:
    """The gather blur's program."""
    return build(device, _KERNEL, [f"-DMIN_SIGMA={MIN_SIGMA_TEXELS}f"])


class OpenCLBlur(DeviceTexture):
    """Separable 2D Gaussian blurs of an RGBA float32 texture with per-texel sigma.

    Buffers for the stretch-derived sigma maps and coverage live on the device for the
    life of the object, so a sequence of blurs of one texture uploads them once.
    """

    def __init__(self, device: Device, coverage: NDArray[Any]) -> None:
        super().__init__(device, *coverage.shape)
        self.kernel = Kernel(_gather_program(device), "blur_axis")
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


def _diffusion_inputs(
    irradiance: NDArray[Any], variances_mm2: NDArray[Any], term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None,
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float32],
           NDArray[np.float32] | None, NDArray[np.bool_], BlurStats]:
    """Checked arrays (E, v, term weights (R, K, 3), region weights or None), which
    terms any present region uses, and stats noting the regions no texel uses."""
    e = _check_irradiance(irradiance)
    rw = None if region_weights is None else \
        unit_region_weights(np.asarray(region_weights, dtype=np.float32))
    v, tw, used, stats = _check_terms(e.shape[:2], variances_mm2, term_weights,
                                      None if rw is None else rw.shape, _region_presence(rw))
    return e, v, tw, rw, used, stats


def diffuse_gather(
    irradiance: NDArray[Any],
    mm_per_texel_u: NDArray[Any],
    mm_per_texel_v: NDArray[Any],
    coverage: NDArray[Any],
    variances_mm2: NDArray[Any],
    term_weights: NDArray[Any],
    region_weights: NDArray[Any] | None = None,
    device: Device | None = None,
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
    blur = OpenCLBlur(or_default(device), cov)
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
