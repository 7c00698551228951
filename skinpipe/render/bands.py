"""Texture-sized numpy steps in bands on the host's cores, and one-off work beside the
main thread.

numpy lets go of the GIL inside its loops, so an elementwise step over a texture at 4096
(16.8 M texels) runs on as many cores as there are bands at once. Between the shadow
rays and the diffusion such steps ran on one core while the other waited (a masked copy
of the irradiance: 0.30 s on one core, 0.14 s in bands on two). Each band's values are
the ones the whole step gives: nothing is summed across bands here.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")

BAND_ITEMS = 1 << 20
"""Rows (or texels) of a band: 4 MB of float32 per column, big enough that a band's
numpy calls cost little beside its work, small enough that bands even out the cores."""


BAND_THREADS = 4
"""Threads that work on bands at once, at most, whatever the core count: these steps
are bound by memory bandwidth, which few cores fill, and each thread that allocates
gets a heap arena of its own from glibc, whose free memory outlives the step (16 band
threads held 0.12 GB more than two through a texture 4096 render's diffusion, its
peak; and 16 bands of a million texels at once hold the whole texture's temporaries)."""


def host_threads() -> int:
    """The cores this process may run on (its CPU affinity, not the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def band_slices(n: int, items: int = BAND_ITEMS) -> list[slice]:
    """``n`` items (rows, texels) as consecutive slices of ``items`` or fewer."""
    items = max(1, int(items))
    return [slice(start, min(start + items, n)) for start in range(0, n, items)]


def in_bands(work: Callable[[slice], T], n: int, items: int = BAND_ITEMS) -> list[T]:
    """``work(band)`` for each band of :func:`band_slices` (``n`` items), on the host's
    cores (:data:`BAND_THREADS` at most); the results in band order. One band, or one
    core: on this thread."""
    bands = band_slices(n, items)
    threads = min(host_threads(), len(bands), BAND_THREADS)
    if threads <= 1:
        return [work(b) for b in bands]
    with ThreadPoolExecutor(threads, thread_name_prefix="skinpipe-bands") as pool:
        return list(pool.map(work, bands))


def beside(work: Callable[[], T], name: str) -> Future[T]:
    """``work()`` started on a thread of its own (named ``name``), which ends with it:
    its future, for the caller to wait on (no thread should outlive the frame that
    started it, not even on errors)."""
    pool = ThreadPoolExecutor(1, thread_name_prefix=name)
    try:
        return pool.submit(work)
    finally:
        pool.shutdown(wait=False)
