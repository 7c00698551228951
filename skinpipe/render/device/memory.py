"""Memory the kernels read and write: device buffers (host memory on a CPU device, huge
pages where they pay), host arrays handed to kernels without a copy, streaming stores
for large outputs, launches over bands of rows, and a device-resident texture."""

from __future__ import annotations

import mmap
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ...errors import InputError
from .choice import Device
from .huge_pages import huge_pages_choice

STREAM_MIN_BYTES = 16 << 20
"""Blurs of images this large write their output with streaming (non-temporal) stores:
a normal store first reads the line it writes, so a texture that will not stay in the
cache anyway is read twice (at 2048^2 RGBA float32, 64 MiB, a quarter to 40% of a
blur's time). Smaller
images are left in the cache for the kernel that reads them next."""


def streams(nbytes: int) -> bool:
    """Whether a blur writing an image of ``nbytes`` uses streaming stores."""
    return nbytes >= STREAM_MIN_BYTES


HUGE_PAGE_MIN_BYTES = 4 << 20
"""Work buffers this large live in host memory backed by 2 MiB pages on a CPU device
(:func:`device_buffer`)."""
_HUGE_PAGE = 2 << 20


@dataclass(frozen=True)
class RowBands:
    """A launch over many rows run ``rows`` rows at a time, ``done(first, stop)`` called
    once each band has run (the queue finished): a kernel that reads arrays mapped from
    the tile store lets each band's pages of them go then, so that it holds a band of
    them, not all (:func:`~.tile_store.drop_resident_pages`)."""

    rows: int
    done: Callable[[int, int], None]


def in_bands(queue: Any, bands: RowBands | None, units: int, rows_per_unit: int,
             launch: Callable[[int, int], None]) -> None:
    """``launch(first, stop)`` over ``units`` work units of ``rows_per_unit`` rows each:
    all at once without ``bands``, else a band of them at a time, the queue finished and
    ``bands.done`` told the band's rows after each."""
    if bands is None:
        launch(0, units)
        return
    per = max(1, bands.rows // rows_per_unit)
    for first in range(0, units, per):
        stop = min(first + per, units)
        launch(first, stop)
        queue.finish()
        bands.done(first * rows_per_unit, stop * rows_per_unit)


def device_buffer(device: Device, size_or_contents: int | NDArray[Any]) -> Any:
    """A read-write device buffer: of that many bytes, or holding that array.

    On a CPU device under Linux, one of :data:`HUGE_PAGE_MIN_BYTES` or more is anonymous
    memory of its own, used in place (``USE_HOST_PTR``), which the kernel is asked to
    back with 2 MiB pages unless their first touch is dearer here
    (:func:`~.huge_pages.huge_pages_choice`; ``madvise(MADV_HUGEPAGE)``: transparent huge
    pages are often enabled for madvised memory only). A recursive pass writes its output
    transposed, one 64-byte line every row-length bytes, so with 4 KiB pages nearly
    every write misses the TLB (measured at 2048^2, the one-sigma recursive blur in one
    process: 47-69 ms with 4 KiB pages, 31-54 ms with 2 MiB pages); and the memory goes
    back to the system when the buffer goes (a buffer of tens of MB from the allocator
    stays resident after it is freed). pyopencl keeps the memory alive as long as the
    buffer; callers finish their queue before they drop a buffer, as every caller here
    does, since the memory goes with the buffer's last reference.
    """
    ctx = device.context
    flags = cl.mem_flags.READ_WRITE
    data = None if isinstance(size_or_contents, int) else \
        np.ascontiguousarray(size_or_contents).reshape(-1).view(np.uint8)
    size = size_or_contents if data is None else data.size
    if size < HUGE_PAGE_MIN_BYTES or not hasattr(mmap, "MADV_HUGEPAGE") \
            or not device.on_host_memory:
        if data is None:
            return cl.Buffer(ctx, flags, size)
        return cl.Buffer(ctx, flags | cl.mem_flags.COPY_HOST_PTR, hostbuf=data)
    region = mmap.mmap(-1, size + _HUGE_PAGE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    if huge_pages_choice().use:
        region.madvise(mmap.MADV_HUGEPAGE)
    raw = np.frombuffer(region, dtype=np.uint8)
    start = (-raw.ctypes.data) % _HUGE_PAGE  # whole huge pages from the first byte
    view = raw[start:start + size]
    if data is not None:
        view[:] = data
    return cl.Buffer(ctx, flags | cl.mem_flags.USE_HOST_PTR, hostbuf=view)


def _over_host(device: Device, array: NDArray[Any], access: Any) -> Any:
    """A buffer over ``array``'s memory on a CPU device (``USE_HOST_PTR``), else a copy of
    it; an empty array gets a one-element buffer (OpenCL has no empty buffers)."""
    data = array if array.size else np.zeros(1, array.dtype)
    how = cl.mem_flags.USE_HOST_PTR if device.on_host_memory else cl.mem_flags.COPY_HOST_PTR
    return cl.Buffer(device.context, access | how, hostbuf=data)


def host_buffer(device: Device, array: NDArray[Any]) -> Any:
    """A read-only device buffer over ``array`` (made C-contiguous): on a CPU device the
    array's own memory (no second copy of, say, 100 MB of region weights; pyopencl
    keeps the array alive as long as the buffer, and nothing may write to it
    meanwhile), elsewhere a copy."""
    return _over_host(device, np.ascontiguousarray(array), cl.mem_flags.READ_ONLY)


def host_output(device: Device, array: NDArray[Any]) -> Any:
    """A device buffer holding ``array``'s values that kernels write the array's new
    contents into: on a CPU device the array's own memory (no copy either way;
    :func:`read_output` makes the array current), elsewhere a copy."""
    if not array.flags.c_contiguous:
        raise InputError("host_output: the array must be C-contiguous")
    return _over_host(device, array, cl.mem_flags.READ_WRITE)


def run_on_host_arrays(kernel: Any, device: Device, global_size: tuple[int, ...],
                       args: Sequence[Any], outputs: Sequence[NDArray[Any]]) -> None:
    """Launch ``kernel`` over ``global_size`` with ``args`` and then ``outputs`` as its
    arguments, and wait for it. Each numpy array among ``args`` is read through
    :func:`host_buffer` (in place on a CPU device) and each of ``outputs`` written
    through :func:`host_output`, current on return. The buffers are held until the
    kernel is done: a buffer over a host array lets the array go with it, while the
    kernel may still read it."""
    held = [host_buffer(device, a) if isinstance(a, np.ndarray) else a for a in args]
    written = [host_output(device, a) for a in outputs]
    kernel(device.queue, global_size, None, *held, *written)
    for buffer, array in zip(written, outputs, strict=True):
        read_output(device, buffer, array)


def read_output(device: Device, buffer: Any, array: NDArray[Any]) -> None:
    """Bring ``array`` up to date with the :func:`host_output` buffer over it: a map and
    unmap of the memory in place on a CPU device, a copy elsewhere (waits for the queue).
    An empty array has nothing to bring (OpenCL refuses to map zero bytes)."""
    queue = device.queue
    if array.size == 0:
        queue.finish()
        return
    if device.on_host_memory:
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

    def __init__(self, device: Device, height: int, width: int) -> None:
        self.device = device
        self.ctx, self.queue = device.context, device.queue
        self.height, self.width = height, width
        self.buf_a = device_buffer(device, height * width * 16)
        self.buf_b = device_buffer(device, height * width * 16)

    def upload(self, image: NDArray[Any]) -> None:
        rgba = np.ascontiguousarray(image, dtype=np.float32)
        if rgba.shape != (self.height, self.width, 4):
            raise InputError(f"texture must be ({self.height}, {self.width}, 4), got {rgba.shape}")
        cl.enqueue_copy(self.queue, self.buf_a, rgba)

    def download(self) -> NDArray[np.float32]:
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
