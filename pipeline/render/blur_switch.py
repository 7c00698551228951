"""Where the direct (FIR) blur stops paying against the recursive one, measured on the
device that runs them.

The direct blur's cost grows with its radius (about 1.5 ms per unit at 2048^2 on PoCL,
two cores), the recursive blur's does not: the switch is the radius where the two
meet. It depends on the runtime, not only on the machine (on PoCL the direct blur
wins up to radius 16; on Intel's CPU runtime the recursive blur at sigma 4 took 29 ms
against the direct blur's 43 ms), so it is measured once per device at
:data:`TUNE_SIZE`^2 (a line through two direct radii against the recursive blur's
best time) and cached on disk, keyed by the device, its driver and skinpipe's
version.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import pyopencl as cl

from .. import __version__
from ..errors import InputError
from .direct_blur import (
    FIR_MAX_RADIUS_PER_TEXEL,
    built_radius,
    direct_kernels,
    direct_radius,
    fir_weight_table,
)
from .opencl import (
    STREAM_MIN_BYTES,
    cl_context,
    device_buffer,
    device_cache,
    device_choice,
    wait_for_prewarm,
)
from .opencl_runtimes import cache_root
from .recursive_blur import iir_kernels, pass_kernels

FIR_MAX_RADIUS_TUNED = 32
"""Widest one-sigma direct kernel the tuner may pick (its ring still fits local memory
with 16-column bands)."""
TUNE_SIZE = 1024
"""Side of the texture the switch is measured on (16 MiB RGBA float32, the demo's own
size: with streaming stores, as a face texture is, and on the kernels a 1024 render
runs anyway, so a cold first render does not compile extra ones for it). Measured here
(PoCL, 2 cores): eight runs in a row gave 11 / 8 every time in 0.4 s each, against
12 / 8-9 at 2048^2 in 1.5 s."""
TUNE_REPEATS = 3
"""Timed runs of each blur; the fastest counts (a shared host only ever adds time)."""
DIRECT_RADII = (4, 11, 16)
"""One-sigma direct radii timed for the line (radius -> ms, least squares)."""
TEXEL_RADII = (4, 7, 11)
"""Per-texel direct radii timed for its line."""


@dataclass(frozen=True)
class DirectLimits:
    """Widest direct kernels that beat the recursive blur on this device (texels)."""

    max_radius: int
    max_radius_per_texel: int
    source: str
    """"measured" (this process), "cache" (measured before on this device) or "fixed"."""
    seconds: float = 0.0
    """Time the measurement took (0 from the cache)."""


def _crossover(radii: tuple[int, ...], direct_ms: tuple[float, ...], recursive_ms: float,
               cap: int) -> int:
    """Largest radius at which the least-squares line through (radius, direct ms) is at
    most the recursive blur's time, within 0..cap."""
    slope, intercept = np.polyfit(np.asarray(radii, float), np.asarray(direct_ms, float), 1)
    if slope <= 0:  # no growth measured: the direct blur wins where it wins at the widest
        return cap if direct_ms[-1] <= recursive_ms else 0
    return int(min(cap, max(0, math.floor((recursive_ms - intercept) / slope + 1e-9))))


def _best_ms(runs: list[Callable[[], None]], queue: object) -> list[float]:
    """Fastest time (ms) of each run, in rounds that take every run in turn (a host
    whose speed drifts then slows all of them alike)."""
    best = [math.inf] * len(runs)
    for n in range(TUNE_REPEATS + 1):
        for k, run in enumerate(runs):
            start = time.perf_counter()
            run()
            queue.finish()  # type: ignore[attr-defined]
            if n:  # the first round builds, JIT-compiles and warms
                best[k] = min(best[k], (time.perf_counter() - start) * 1e3)
    return best


def _sigma_for_radius(radius: int) -> float:
    """A sigma (texels) whose direct kernel has ``radius`` (the largest such sigma)."""
    lo, hi = 0.3, 64.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if direct_radius(mid) <= radius else (lo, mid)
    return lo


def measure_direct_limits(size: int = TUNE_SIZE) -> DirectLimits:
    """Time the direct and recursive blurs on this device and return where they meet."""
    wait_for_prewarm()  # compilations on the other core would slow what is timed
    start = time.perf_counter()
    ctx, queue = cl_context()
    rng = np.random.default_rng(0)
    src = device_buffer(rng.random((size, size, 4), dtype=np.float32))
    tmp, dst = device_buffer(size * size * 16), device_buffer(size * size * 16)
    iir, direct = iir_kernels(), direct_kernels()
    co = iir.coefficients(4.0)
    sigmas = [_sigma_for_radius(r) for r in DIRECT_RADII]
    radii = tuple(direct_radius(s) for s in sigmas)
    # per texel: two table rows, every texel on row 0 (the cost does not depend on which)
    flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
    rows16 = cl.Buffer(ctx, flags, hostbuf=np.zeros(size * size, np.uint16))
    rows32 = cl.Buffer(ctx, flags, hostbuf=np.zeros(size * size, np.int32))
    co_t = iir.coefficients(np.array([4.0, 4.1]))
    tables = [fir_weight_table(np.array([0.6, 1.0]) * _sigma_for_radius(r))
              for r in TEXEL_RADII]
    texel_radii = tuple(t.shape[1] - 1 for t in tables)
    runs: list[Callable[[], None]] = [
        lambda: iir.blur(src, tmp, dst, size, size, co, co),
        lambda: iir.blur(src, tmp, dst, size, size, co_t, co_t, rows32, rows32),
        *(lambda s=s: direct.blur(src, dst, size, size, s, s) for s in sigmas),
        *(lambda t=t: direct.blur_per_texel(src, dst, size, size, t, t, rows16, rows16)
          for t in tables)]
    ms = _best_ms(runs, queue)
    recursive, recursive_t = ms[0], ms[1]
    one, per_texel = tuple(ms[2:2 + len(sigmas)]), tuple(ms[2 + len(sigmas):])
    return DirectLimits(
        _crossover(radii, one, recursive, FIR_MAX_RADIUS_TUNED),
        _crossover(texel_radii, per_texel, recursive_t, FIR_MAX_RADIUS_PER_TEXEL),
        "measured", time.perf_counter() - start)


def tuning_kernels() -> list[Any]:
    """The kernels :func:`measure_direct_limits` times (for :class:`~.opencl.Prewarm`)."""
    stream = TUNE_SIZE * TUNE_SIZE * 16 >= STREAM_MIN_BYTES
    direct = direct_kernels()
    one = [built_radius(direct_radius(_sigma_for_radius(r))) for r in DIRECT_RADII]
    return [*pass_kernels(stream), *(direct.kernel(r, r, stream) for r in one),
            *(direct.kernel(r, r, stream, True) for r in TEXEL_RADII)]


def _cache_path() -> str:
    d = device_choice().device
    key = "|".join(str(x) for x in (device_choice().candidate.label, d.driver_version,
                                    d.version, d.max_compute_units, __version__, TUNE_SIZE))
    name = hashlib.sha256(key.encode()).hexdigest()[:16]
    return os.path.join(cache_root(), "opencl", f"blur-switch-{name}.json")


SWITCH_ENV = "SKINPIPE_BLUR_SWITCH"
"""``R,RT``: fix the switch (widest one-sigma and per-texel direct radius) instead of
measuring it, e.g. so that every node of a mixed farm runs the same kernels."""


def fixed_limits(text: str) -> DirectLimits:
    """The switch ``R,RT`` of :data:`SWITCH_ENV`."""
    try:
        r, rt = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"${SWITCH_ENV} must be two radii 'R,RT', got {text!r}") from None
    if not (0 <= r <= FIR_MAX_RADIUS_TUNED and 0 <= rt <= FIR_MAX_RADIUS_PER_TEXEL):
        raise InputError(f"${SWITCH_ENV}: radii must be 0-{FIR_MAX_RADIUS_TUNED} and "
                         f"0-{FIR_MAX_RADIUS_PER_TEXEL}, got {text!r}")
    return DirectLimits(r, rt, "fixed")


def known_limits() -> DirectLimits | None:
    """The switch from :data:`SWITCH_ENV` or the disk cache; None if it must be measured."""
    if os.environ.get(SWITCH_ENV):
        return fixed_limits(os.environ[SWITCH_ENV])
    try:
        with open(_cache_path(), encoding="utf-8") as f:
            saved = json.load(f)
        return DirectLimits(int(saved["max_radius"]), int(saved["max_radius_per_texel"]),
                            "cache")
    except (OSError, ValueError, KeyError, TypeError):
        return None


@device_cache()
def direct_limits() -> DirectLimits:
    """The switch for the chosen device: :data:`SWITCH_ENV` if set, else from the disk
    cache, else measured (about a second) and stored."""
    known = known_limits()
    if known is not None:
        return known
    path = _cache_path()
    limits = measure_direct_limits()
    try:
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=os.path.dirname(path), suffix=".tmp")
        with os.fdopen(fd, "w", encoding="utf-8") as f:
            json.dump(asdict(limits), f)
        os.replace(tmp, path)
    except OSError:
        pass  # a read-only cache costs a measurement per process, nothing else
    return limits


def prefers_direct(sigma_u: float, sigma_v: float, per_texel: bool = False,
                   limits: DirectLimits | None = None) -> bool:
    """Whether the direct blur is the faster one for these sigmas (texels; per texel: the
    widest) on this device: both radii within :func:`direct_limits`."""
    lim = limits or direct_limits()
    limit = lim.max_radius_per_texel if per_texel else lim.max_radius
    return max(direct_radius(sigma_u), direct_radius(sigma_v)) <= limit
