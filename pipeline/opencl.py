"""The OpenCL device every texture-space kernel runs on: the first CPU device (PoCL
from ``pyopencl[pocl]``), else any device; compiled kernels are cached on disk."""

from __future__ import annotations

import mmap
import os
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .errors import InputError

STREAM_MIN_BYTES = 16 << 20
"""Blurs of images this large write their output with streaming (non-temporal) stores:
a normal store first reads the line it writes, so a texture that will not stay in the
cache anyway is read twice (measured at 2048^2 RGBA float32, 64 MiB: the one-sigma
recursive blur 45-47 -> 34-36 ms, the direct blur at sigma 1 17 -> 10 ms). Smaller
images are left in the cache for the kernel that reads them next."""
HUGE_PAGE_MIN_BYTES = 4 << 20
"""Work buffers this large live in host memory backed by 2 MiB pages on a CPU device
(:func:`device_buffer`)."""
_HUGE_PAGE = 2 << 20
STORE_MACRO = r"""
#if STREAM
#define STORE(v, p) __builtin_nontemporal_store((v), (p))
#else
#define STORE(v, p) (*(p) = (v))
#endif
"""


@lru_cache(maxsize=1)
def cl_context() -> tuple[Any, Any]:
    """(context, in-order queue), made once per process."""
    import pyopencl as cl

    os.environ.setdefault("POCL_CACHE_DIR", os.path.join(
        os.path.expanduser("~"), ".cache", "skinpipe", "pocl"))
    devices = [d for p in cl.get_platforms() for d in p.get_devices()]
    if not devices:
        raise InputError("no OpenCL device: install pyopencl[pocl] for a CPU device")
    cpu = [d for d in devices if d.type & cl.device_type.CPU]
    ctx = cl.Context([(cpu or devices)[0]])
    return ctx, cl.CommandQueue(ctx)


def build(source: str, options: list[str] | None = None) -> Any:
    """A program for the shared context (callers cache what they build)."""
    import pyopencl as cl

    ctx, _ = cl_context()
    return cl.Program(ctx, source).build(options=options or [])


@lru_cache(maxsize=1)
def _host_memory_device() -> bool:
    """Whether the device runs on this machine's memory (a CPU device: PoCL)."""
    import pyopencl as cl

    ctx, _ = cl_context()
    return bool(ctx.devices[0].type & cl.device_type.CPU)


def device_buffer(size_or_contents: int | NDArray[Any]) -> Any:
    """A read-write device buffer: of that many bytes, or holding that array.

    On a CPU device under Linux, one of :data:`HUGE_PAGE_MIN_BYTES` or more is anonymous
    memory of its own, which the kernel is asked to back with 2 MiB pages
    (``madvise(MADV_HUGEPAGE)``: transparent huge pages are often enabled for madvised
    memory only), used in place (``USE_HOST_PTR``). A recursive pass writes its output
    transposed, one 64-byte line every row-length bytes, so with 4 KiB pages nearly
    every write misses the TLB (measured at 2048^2, the one-sigma recursive blur in one
    process: 47-69 ms with 4 KiB pages, 31-54 ms with 2 MiB pages); and the memory goes
    back to the system when the buffer goes (a buffer of tens of MB from the allocator
    stays resident after it is freed). pyopencl keeps the memory alive as long as the
    buffer; callers finish their queue before they drop a buffer, as every caller here
    does, since the memory goes with the buffer's last reference.
    """
    import pyopencl as cl

    ctx, _ = cl_context()
    flags = cl.mem_flags.READ_WRITE
    data = None if isinstance(size_or_contents, int) else \
        np.ascontiguousarray(size_or_contents).reshape(-1).view(np.uint8)
    size = size_or_contents if data is None else data.size
    if size < HUGE_PAGE_MIN_BYTES or not hasattr(mmap, "MADV_HUGEPAGE") \
            or not _host_memory_device():
        if data is None:
            return cl.Buffer(ctx, flags, size)
        return cl.Buffer(ctx, flags | cl.mem_flags.COPY_HOST_PTR, hostbuf=data)
    region = mmap.mmap(-1, size + _HUGE_PAGE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    region.madvise(mmap.MADV_HUGEPAGE)
    raw = np.frombuffer(region, dtype=np.uint8)
    start = (-raw.ctypes.data) % _HUGE_PAGE  # whole huge pages from the first byte
    view = raw[start:start + size]
    if data is not None:
        view[:] = data
    return cl.Buffer(ctx, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=view)


def _over_host(array: NDArray[Any], access: Any) -> Any:
    """A buffer over ``array``'s memory on a CPU device (``USE_HOST_PTR``), else a copy of
    it; an empty array gets a one-element buffer (OpenCL has no empty buffers)."""
    import pyopencl as cl

    ctx, _ = cl_context()
    data = array if array.size else np.zeros(1, array.dtype)
    how = cl.mem_flags.USE_HOST_PTR if _host_memory_device() else cl.mem_flags.COPY_HOST_PTR
    return cl.Buffer(ctx, access | how, hostbuf=data)


def host_buffer(array: NDArray[Any]) -> Any:
    """A read-only device buffer over ``array`` (made C-contiguous): on a CPU device the
    array's own memory (no second copy of, say, 100 MB of region weights; pyopencl
    keeps the array alive as long as the buffer, and nothing may write to it
    meanwhile), elsewhere a copy."""
    import pyopencl as cl

    return _over_host(np.ascontiguousarray(array), cl.mem_flags.READ_ONLY)


def host_output(array: NDArray[Any]) -> Any:
    """A device buffer holding ``array``'s values that kernels write the array's new
    contents into: on a CPU device the array's own memory (no copy either way;
    :func:`read_output` makes the array current), elsewhere a copy."""
    import pyopencl as cl

    if not array.flags.c_contiguous:
        raise InputError("host_output: the array must be C-contiguous")
    return _over_host(array, cl.mem_flags.READ_WRITE)


def read_output(queue: Any, buffer: Any, array: NDArray[Any]) -> None:
    """Bring ``array`` up to date with the :func:`host_output` buffer over it: a map and
    unmap of the memory in place on a CPU device, a copy elsewhere (waits for the queue)."""
    import pyopencl as cl

    if _host_memory_device():
        mapped, _ = cl.enqueue_map_buffer(queue, buffer, cl.map_flags.READ, 0, array.shape,
                                          array.dtype)
        mapped.base.release(queue)
        queue.finish()
    else:
        cl.enqueue_copy(queue, array, buffer)


class DeviceTexture:
    """An RGBA float32 texture on the device (``buf_a``) and a second buffer of its size
    (``buf_b``) for the work between passes: what every blur class holds. Subclasses
    implement ``blur_in_place`` (sigmas in texels), leaving the result in ``buf_a``."""

    def __init__(self, height: int, width: int) -> None:
        self.ctx, self.queue = cl_context()
        self.height, self.width = height, width
        self.buf_a = device_buffer(height * width * 16)
        self.buf_b = device_buffer(height * width * 16)

    def upload(self, image: NDArray[Any]) -> None:
        import pyopencl as cl

        rgba = np.ascontiguousarray(image, dtype=np.float32)
        if rgba.shape != (self.height, self.width, 4):
            raise InputError(f"texture must be ({self.height}, {self.width}, 4), got {rgba.shape}")
        cl.enqueue_copy(self.queue, self.buf_a, rgba)

    def download(self) -> NDArray[np.float32]:
        import pyopencl as cl

        out = np.empty((self.height, self.width, 4), dtype=np.float32)
        cl.enqueue_copy(self.queue, out, self.buf_a)
        return out

    def blur_in_place(self, sigma_u: Any, sigma_v: Any) -> None:
        raise NotImplementedError

    def blur(self, image: NDArray[Any], sigma_u: Any, sigma_v: Any) -> NDArray[np.float32]:
        """Upload ``image``, blur it, return the result."""
        self.upload(image)
        self.blur_in_place(sigma_u, sigma_v)
        return self.download()
