"""Recursive (IIR) Gaussian blur in OpenCL whose cost does not grow with sigma.

Deriche (1993), "Recursively implementing the Gaussian and its derivatives", INRIA
RR-1893: the Gaussian as a 4th-order causal plus a 4th-order anticausal recursive
filter (run as two second-order sections each way, for float32), 16 multiply-adds
per sample and channel whatever sigma is. Measured here
against the exact sampled Gaussian: 3.5e-4 of the peak at most for sigma 0.5-64
texels (1D). Its variance is 0.45% short of sigma^2 (in the tails); the sigma parameter
is solved for the exact variance below 0.8 texel (closed form of the second moment from
the poles), where sampling makes any short filter narrower than sigma^2.

Coefficients vary per texel (sigma from the stretch map): per-texel sigmas are kept on
a log2 grid of 1/1024 octave, each texel holds an index, and the coefficients of each
index in use are interpolated on the host from a table over log2(sigma) (64 entries per
octave) and loaded by the kernel per texel. Chart borders are
handled by normalised convolution: alpha carries the coverage, RGB the irradiance
times coverage, and a term is RGB / alpha after the blur, so uncovered texels give
nothing and take nothing.
"""

from __future__ import annotations

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

# Deriche 1993's fit of exp(-x^2 / 2) for x >= 0 (x in units of sigma):
# sum over the pairs of (a cos(w x) + b sin(w x)) exp(-lam x)
DERICHE_1993 = ((1.6797292232361107, 3.7348298269103593, 1.7831906604375575, 0.6318113174569493),
                (-0.6802783501655264, -0.2598300478959625, 1.7228297663338028,
                 1.9969276058886463))
TABLE_MIN_SIGMA = 0.25
TABLE_OCTAVES = 13  # up to 0.25 * 2^13 = 2048 texels
TABLE_STEPS_PER_OCTAVE = 64
LINES_PER_ITEM = 4
"""Rows one work item filters side by side (measured per 2D blur at 2048^2, per-texel
coefficients: 1 row 40-42 ms, 2 rows 33 ms, 4 rows 32-36 ms; 8 rows spill registers)."""
QUANT_STEPS_PER_OCTAVE = 1024


def _poles(sigma: Any) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Residues c_k (4,) and poles p_k (..., 4) with h(n) = sum_k c_k p_k^n for n >= 0,
    for a scalar or an array of sigmas."""
    cs, rates = [], []
    for a, b, lam, w in DERICHE_1993:
        c = complex(a, -b) / 2
        cs += [c, np.conj(c)]
        rates += [complex(-lam, w), complex(-lam, -w)]
    s = np.asarray(sigma, np.float64)[..., None]
    return np.array(cs), np.exp(np.array(rates) / s)


def deriche_variance(sigma: Any) -> Any:
    """Variance (texels^2) of the sampled Deriche filter with parameter ``sigma`` (scalar
    or array): sum n^2 p^n = p (1 + p) / (1 - p)^3 over each pole, both halves."""
    c, p = _poles(sigma)
    h0 = c.sum().real
    mass = (2 * (c / (1 - p)).sum(axis=-1) - h0).real
    second = (2 * (c * p * (1 + p) / (1 - p) ** 3).sum(axis=-1)).real
    out = second / mass
    return float(out) if np.ndim(sigma) == 0 else out


def deriche_coefficients(sigma: float) -> NDArray[np.float64]:
    """Two second-order sections in parallel, one per conjugate pole pair: for each,
    (b0, b1, m1, m2, a1, a2) of y+[i] = b0 x[i] + b1 x[i-1] - a1 y+[i-1] - a2 y+[i-2]
    and y-[i] = m1 x[i+1] + m2 x[i+2] - a1 y-[i+1] - a2 y-[i+2]; y = sum of all four,
    normalised to unit sum. (The direct 4th-order form loses 5e-3 of the peak to
    float32 rounding of its coefficients; the parallel form keeps 1e-4.)"""
    c, p = _poles(float(sigma))
    rows = []
    for k in (0, 2):
        ck, pk = c[k], p[k]
        rows.append([2 * ck.real, -2 * (ck * np.conj(pk)).real, 2 * (ck * pk).real,
                     -2 * abs(pk) ** 2 * ck.real, -2 * pk.real, abs(pk) ** 2])
    co = np.array(rows)
    total = sum((r[0] + r[1] + r[2] + r[3]) / (1 + r[4] + r[5]) for r in co)
    co[:, :4] /= total
    return co.reshape(-1)


@lru_cache(maxsize=1)
def coefficient_table() -> NDArray[np.float32]:
    """(entries, 12) section coefficients for sigma = TABLE_MIN_SIGMA * 2^(i / steps)."""
    n = TABLE_OCTAVES * TABLE_STEPS_PER_OCTAVE + 1
    targets = TABLE_MIN_SIGMA * 2.0 ** (np.arange(n) / TABLE_STEPS_PER_OCTAVE)
    # variance of the filter against its parameter, on a finer grid, inverted
    params = TABLE_MIN_SIGMA * 0.5 * 2.0 ** (
        np.arange(4 * (n + 2 * TABLE_STEPS_PER_OCTAVE)) / (4 * TABLE_STEPS_PER_OCTAVE))
    # below a quarter texel the filter is a near-delta whose variance rounds to <= 0
    sd = np.maximum.accumulate(np.sqrt(np.maximum(deriche_variance(params), 0)))
    matched = np.interp(targets, sd, params)
    # Deriche's shape follows the Gaussian near the peak and is 0.45% short in variance
    # (its tails); matching the variance would cost 2e-3 at the peak. Below 0.8 texel
    # the sampled filter is far narrower than sigma^2 (0.21 vs 0.25 at 0.5): there the
    # variance is matched, as the gather kernel's parameter is (blend 0.5 - 0.8).
    t = np.clip((targets - 0.5) / 0.3, 0.0, 1.0)
    fitted = (1 - t) * matched + t * targets
    return np.array([deriche_coefficients(s) for s in fitted], dtype=np.float32)


def table_position(sigma: NDArray[Any]) -> NDArray[np.float64]:
    """Fractional table index of each sigma (texels), clamped to the table."""
    s = np.clip(np.asarray(sigma, np.float64), TABLE_MIN_SIGMA,
                TABLE_MIN_SIGMA * 2.0 ** TABLE_OCTAVES)
    return np.log2(s / TABLE_MIN_SIGMA) * TABLE_STEPS_PER_OCTAVE


def _coefficients_at(sigma: NDArray[Any]) -> NDArray[np.float64]:
    table = coefficient_table().astype(np.float64)
    t = table_position(sigma)
    i = np.minimum(np.floor(t).astype(np.int64), table.shape[0] - 2)
    f = (t - i)[..., None]
    return table[i] * (1 - f) + table[i + 1] * f


def recursive_reference(image: NDArray[Any], sigma_u: NDArray[Any], sigma_v: NDArray[Any]
                        ) -> NDArray[np.float64]:
    """float64 numpy version of :class:`RecursiveBlur` (u pass, then v pass) for per-texel
    sigma maps (H, W): sigma on the kernel's quantised grid, coefficients interpolated
    from the same table. For tests and small images."""
    out = np.asarray(image, np.float64)
    for axis, sigma in ((1, sigma_u), (0, sigma_v)):
        x = np.moveaxis(out, axis, 0)           # lines along axis 0
        co = np.moveaxis(_coefficients_at(quantized_sigma(sigma)), axis, 0)[..., None]
        n = x.shape[0]
        total = np.zeros_like(x)
        for sec in (0, 6):
            b0, b1, m1, m2, a1, a2 = (co[..., sec + j, :] for j in range(6))
            y = np.zeros_like(x)
            for i in range(n):
                y[i] = b0[i] * x[i]
                if i >= 1:
                    y[i] += b1[i] * x[i - 1] - a1[i] * y[i - 1]
                if i >= 2:
                    y[i] -= a2[i] * y[i - 2]
            total += y
            y = np.zeros_like(x)
            for i in range(n - 1, -1, -1):
                if i + 1 < n:
                    y[i] = m1[i] * x[i + 1] - a1[i] * y[i + 1]
                if i + 2 < n:
                    y[i] += m2[i] * x[i + 2] - a2[i] * y[i + 2]
            total += y
        out = np.moveaxis(total, 0, axis)
    return out


_KERNEL = cl_source(__package__, "recursive_blur.cl")


QUANTIZE_CHUNK = 1 << 18
"""Values :func:`quantized_log2` takes at a time (a multiple of any SIMD width, so that
each value goes through numpy's loops as in one whole-array call): the temporaries stay
in cache, where whole arrays' were three fresh texel-size maps. The layout's ten calls
at texture 4096 (53 M atlas texels) took 0.59-0.68 s, these 0.37-0.39 s."""


def quantized_log2(x: NDArray[Any]) -> NDArray[np.int32]:
    """round(QUANT_STEPS_PER_OCTAVE log2 x): where per-texel blurs keep their sigma (or
    texel size), within 0.034% (the coefficients of neighbouring texels are shared)."""
    values = np.asarray(x)
    flat = values.reshape(-1)
    out = np.empty(flat.shape, np.int32)
    for s in range(0, flat.size, QUANTIZE_CHUNK):
        part = np.log2(flat[s:s + QUANTIZE_CHUNK])
        part *= QUANT_STEPS_PER_OCTAVE
        out[s:s + QUANTIZE_CHUNK] = np.rint(part, out=part)
    return out.reshape(values.shape)[()]  # a scalar's is a scalar, as numpy's


def quantized_sigma(sigma: NDArray[Any]) -> NDArray[np.float64]:
    """Sigma (texels) as the per-texel kernel applies it: on the quantized log2 grid,
    clamped to the coefficient table."""
    s = np.clip(np.asarray(sigma, np.float64), TABLE_MIN_SIGMA,
                TABLE_MIN_SIGMA * 2.0 ** TABLE_OCTAVES)
    return 2.0 ** (quantized_log2(s) / QUANT_STEPS_PER_OCTAVE)


def _variant_name(uniform: bool, stream: bool, global_scratch: bool = False) -> str:
    return f"iir_rows_transposed_{int(uniform)}{int(stream)}" + ("_g" if global_scratch else "")


def _variant_source(uniform: bool, stream: bool, global_scratch: bool = False) -> str:
    """The pass for one sigma or per-texel coefficients, with or without streaming
    stores, its scratch rows in local or global memory, as :func:`_variant_name`."""
    return (f"#define UNIFORM {int(uniform)}\n#define STREAM {int(stream)}\n"
            f"#define GLOBAL_SCRATCH {int(global_scratch)}\n"
            f"#define LINES {LINES_PER_ITEM}\n" + STORE_MACRO
            + _KERNEL.replace("iir_rows_transposed(",
                              _variant_name(uniform, stream, global_scratch) + "(")
            + "#undef UNIFORM\n#undef STREAM\n#undef LINES\n#undef STORE\n#undef COEFFS\n"
            "#undef GLOBAL_SCRATCH\n#undef SCRATCH_SPACE\n")


@lru_cache(maxsize=8)
def _iir_kernel(device: Device, uniform: bool, stream: bool, global_scratch: bool = False
                ) -> Any:
    """The recursive pass for one sigma or per-texel coefficients, with or without
    streaming stores, its scratch in local memory (or global, :class:`IIRKernels`).
    Where kernels are compiled at their first launch (PoCL) the four local ones are in
    one program: its build's fixed cost (0.29 s cold, measured, whatever the program
    holds) is paid once; elsewhere (Intel's runtime compiles every kernel of a program
    when it builds it), and for global scratch, each is a program of its own, built
    when first needed."""
    variants = [(u, s) for u in (True, False) for s in (True, False)] \
        if device.jit_at_first_launch and not global_scratch else [(uniform, stream)]
    program = build(device, "".join(_variant_source(u, s, global_scratch) for u, s in variants))
    return Kernel(program, _variant_name(uniform, stream, global_scratch), (1,))


def pass_kernels(device: Device, stream: bool, uniform: bool = False) -> list[Any]:
    """The per-texel (or one-sigma) recursive pass with or without streaming stores (for
    :class:`~.opencl.Prewarm`; a face's layout runs per-texel blurs)."""
    return [_iir_kernel(device, uniform, stream)]


class IIRKernels:
    """The built recursive-pass kernels (one sigma, per texel); one per process
    (:func:`iir_kernels`)."""

    def __init__(self, device: Device) -> None:
        self.device = device
        self.ctx, self.queue = device.context, device.queue
        self.max_line = int(self.ctx.devices[0].local_mem_size) // (16 * LINES_PER_ITEM)
        """The longest row whose scratch fits local memory; longer rows' scratch is a
        global buffer (:meth:`_global_scratch`)."""
        self._scratch: Any = None

    def coefficients(self, sigma: NDArray[Any]) -> Any:
        """Device buffer of the section coefficients (N, 12) for sigmas (N,) in texels."""
        co = _coefficients_at(np.atleast_1d(np.asarray(sigma, np.float64))).astype(np.float32)
        return cl.Buffer(self.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                         hostbuf=np.ascontiguousarray(co))

    def run_pass(self, src: Any, dst: Any, n: int, lines: int, coefs: Any,
                 index: Any = None, row_bands: RowBands | None = None) -> None:
        """Enqueue one pass over ``lines`` rows of ``n`` float4 texels of ``src`` into
        ``dst``, transposed; ``row_bands``: a band of rows at a time
        (:class:`~.opencl.RowBands`)."""
        # the one-sigma kernel never reads `index`: any buffer fills the argument
        stream = streams(n * lines * 16)
        items = -(-lines // LINES_PER_ITEM)
        in_global = n > self.max_line
        kernel = _iir_kernel(self.device, index is None, stream, in_global)
        scratch = self._global_scratch(16 * LINES_PER_ITEM * n * items) if in_global else \
            cl.LocalMemory(16 * LINES_PER_ITEM * n)
        args = (src, dst, scratch,
                coefs if index is None else index, coefs, np.int32(n), np.int32(lines))
        in_bands(self.queue, row_bands, items, LINES_PER_ITEM, lambda i0, i1: kernel(
            self.queue, (i1 - i0,), (1,), *args, global_offset=(i0,)))

    def _global_scratch(self, nbytes: int) -> Any:
        """A global buffer of at least ``nbytes`` for the passes whose rows are longer
        than local memory holds (each work item its LINES rows), kept for the next
        such pass; the queue is in order, so passes share it."""
        if self._scratch is None or self._scratch.size < nbytes:
            self._scratch = None  # its memory goes before the larger one comes
            self._scratch = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)
        return self._scratch

    def blur(self, src: Any, tmp: Any, dst: Any, height: int, width: int,
             coefs_u: Any, coefs_v: Any, index_u: Any = None, index_v_t: Any = None,
             row_bands: tuple[RowBands, RowBands] | None = None) -> None:
        """Enqueue one 2D blur of the (height, width) float4 image ``src`` into ``dst``
        (``tmp`` holds it transposed between the passes; src may be dst). Each texel
        uses entry index[texel] of the coefficient buffer (index_u in row layout,
        index_v_t transposed), or entry 0 where the index is None. ``row_bands``: each
        pass a band of its rows at a time (:class:`~.opencl.RowBands`)."""
        bands_u, bands_v = row_bands or (None, None)
        self.run_pass(src, tmp, width, height, coefs_u, index_u, bands_u)
        self.run_pass(tmp, dst, height, width, coefs_v, index_v_t, bands_v)


@lru_cache(maxsize=4)
def iir_kernels(device: Device) -> IIRKernels:
    return IIRKernels(device)


class RecursiveBlur(DeviceTexture):
    """Separable recursive Gaussian blurs of an RGBA float32 texture on the device.

    ``blur_in_place(sigma_u, sigma_v)`` takes per-texel maps or scalars (texels); a
    scalar runs the one-sigma kernel. Cost per texel is the same for any sigma.
    """

    def __init__(self, device: Device, height: int, width: int) -> None:
        super().__init__(device, height, width)
        self.iir = iir_kernels(device)

    def _pass(self, sigma: Any, transposed: bool) -> tuple[Any, Any]:
        """(coefficient buffer, index buffer or None) for a scalar sigma or a map."""
        if np.ndim(sigma) == 0:
            return self.iir.coefficients(float(sigma)), None
        s = np.asarray(sigma, np.float64)
        if s.shape != (self.height, self.width):
            raise InputError(f"sigma map must be ({self.height}, {self.width}), got {s.shape}")
        q = quantized_log2(quantized_sigma(s))
        lo = int(q.min())
        index = (q - lo).T if transposed else q - lo
        steps = np.arange(int(q.max()) - lo + 1)
        coefs = self.iir.coefficients(2.0 ** ((lo + steps) / QUANT_STEPS_PER_OCTAVE))
        buf = cl.Buffer(self.iir.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                        hostbuf=np.ascontiguousarray(index, np.int32))
        return coefs, buf

    def blur_in_place(self, sigma_u: Any, sigma_v: Any) -> None:
        coefs_u, index_u = self._pass(sigma_u, False)
        coefs_v, index_v = self._pass(sigma_v, True)
        self.iir.blur(self.buf_a, self.buf_b, self.buf_a, self.height, self.width,
                      coefs_u, coefs_v, index_u, index_v)
        self.queue.finish()
