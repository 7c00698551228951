"""The OpenCL device every texture-space kernel runs on: the first CPU device (PoCL
from ``pyopencl[pocl]``), else any device; compiled kernels are cached on disk."""

from __future__ import annotations

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


class DeviceTexture:
    """An RGBA float32 texture on the device (``buf_a``) and a second buffer of its size
    (``buf_b``) for the work between passes: what every blur class holds. Subclasses
    implement ``blur_in_place`` (sigmas in texels), leaving the result in ``buf_a``."""

    def __init__(self, height: int, width: int) -> None:
        import pyopencl as cl

        self.ctx, self.queue = cl_context()
        self.height, self.width = height, width
        nbytes = height * width * 16
        self.buf_a = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)
        self.buf_b = cl.Buffer(self.ctx, cl.mem_flags.READ_WRITE, nbytes)

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
