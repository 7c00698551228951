"""Whether a render fits in this machine's memory, asked before it starts.

A render holds texture-sized maps, its diffusion's atlases and pyramid, and image-sized
camera hits and AOVs. Its peak grows with both sizes; measured on the demo face with
``/usr/bin/time`` (a first render, which makes its seam layout, the larger case):
about 165 bytes a texel (2.7 GB at texture 4096) and 205 bytes an image pixel (0.80 GB
more from 512^2 to 2048^2 pixels), over 0.5 GB for the interpreter and its libraries.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

from ..errors import InputError

BYTES_PER_TEXEL = 165
BYTES_PER_PIXEL = 205
BASE_BYTES = 512 << 20


def render_bytes(texture_size: int, resolution: tuple[int, int]) -> int:
    """The estimated peak resident memory of one render, bytes."""
    w, h = resolution
    return BASE_BYTES + BYTES_PER_TEXEL * texture_size ** 2 + BYTES_PER_PIXEL * w * h


def available_bytes() -> int | None:
    """Memory the kernel says a new allocation can get without swapping (MemAvailable),
    bounded by a cgroup v2 limit where one is set; None where neither can be read."""
    figures = []
    with contextlib.suppress(OSError, ValueError, IndexError, StopIteration):
        meminfo = Path("/proc/meminfo").read_text().splitlines()
        line = next(x for x in meminfo if x.startswith("MemAvailable:"))
        figures.append(int(line.split()[1]) * 1024)
    with contextlib.suppress(OSError, ValueError):
        cgroup = Path("/sys/fs/cgroup")
        limit = (cgroup / "memory.max").read_text().strip()
        if limit != "max":
            figures.append(int(limit) - int((cgroup / "memory.current").read_text()))
    return min(figures) if figures else None


def check_render_fits(texture_size: int, resolution: tuple[int, int],
                      available: int | None = None) -> int:
    """Refuse (InputError) a render whose estimated peak exceeds the memory available;
    return the estimate. ``SKINPIPE_MEMORY_CHECK=off`` skips the refusal (a machine whose
    swap the user means to use)."""
    need = render_bytes(texture_size, resolution)
    have = available_bytes() if available is None else available
    if have is None or os.environ.get("SKINPIPE_MEMORY_CHECK", "").lower() == "off":
        return need
    if need > have:
        w, h = resolution
        raise InputError(
            f"a render at texture {texture_size} and {w}x{h} pixels needs about "
            f"{need / 2**30:.1f} GiB, and this machine has {have / 2**30:.1f} GiB available: "
            "use a smaller --texture-size or --resolution (SKINPIPE_MEMORY_CHECK=off "
            "renders anyway)")
    return need
