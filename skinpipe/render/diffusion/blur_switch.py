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

import contextlib
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

from ... import __version__
from ...errors import InputError
from ..cache import entry_name, kind_folder, read_json_entry, reject, write_json_entry
from ..device.choice import Device
from ..device.memory import device_buffer, streams
from ..device.programs import wait_for_prewarm
from .direct_blur import (
    FIR_MAX_RADIUS_PER_TEXEL,
    direct_kernels,
    direct_radius,
    fir_weight_table,
)
from .recursive_blur import iir_kernels

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
TEXEL_RADII = (4, 7)
"""Per-texel direct radii timed for its line: two that a face's render runs anyway (a
third, 11, costs a cold render a compilation, 0.35 s on PoCL, and moved nothing:
eight measurements each gave 8-9 on PoCL with and without it, 8-11 and 9-11 on
Intel's runtime)."""


@dataclass(frozen=True)
class DirectLimits:
    """Widest direct kernels that beat the recursive blur on this device (texels); None
    for a kind not measured (each kind is measured when a blur of it first asks)."""

    max_radius: int | None
    max_radius_per_texel: int | None
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


def measure_direct_limits(device: Device, size: int = TUNE_SIZE, one_sigma: bool = True,
                          per_texel: bool = True) -> DirectLimits:
    """Time the direct and recursive blurs on this device and return where they meet,
    for one-sigma and/or per-texel blurs (a kind not asked for: None, and none of its
    kernels built)."""
    wait_for_prewarm()  # compilations on the other core would slow what is timed
    start = time.perf_counter()
    ctx, queue = device.context, device.queue
    rng = np.random.default_rng(0)
    src = device_buffer(device, rng.random((size, size, 4), dtype=np.float32))
    tmp, dst = device_buffer(device, size * size * 16), device_buffer(device, size * size * 16)
    iir, direct = iir_kernels(device), direct_kernels(device)
    runs: list[Callable[[], None]] = []
    if one_sigma:
        co = iir.coefficients(4.0)
        sigmas = [_sigma_for_radius(r) for r in DIRECT_RADII]
        radii = tuple(direct_radius(s) for s in sigmas)
        runs += [lambda: iir.blur(src, tmp, dst, size, size, co, co),
                 *(lambda s=s: direct.blur(src, dst, size, size, s, s) for s in sigmas)]
    if per_texel:
        # two table rows, every texel on row 0 (the cost does not depend on which)
        flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
        rows16 = cl.Buffer(ctx, flags, hostbuf=np.zeros(size * size, np.uint16))
        rows32 = cl.Buffer(ctx, flags, hostbuf=np.zeros(size * size, np.int32))
        co_t = iir.coefficients(np.array([4.0, 4.1]))
        tables = [fir_weight_table(np.array([0.6, 1.0]) * _sigma_for_radius(r))
                  for r in TEXEL_RADII]
        texel_radii = tuple(t.shape[1] - 1 for t in tables)
        runs += [lambda: iir.blur(src, tmp, dst, size, size, co_t, co_t, rows32, rows32),
                 *(lambda t=t: direct.blur_per_texel(src, dst, size, size, t, t, rows16,
                                                     rows16) for t in tables)]
    ms = _best_ms(runs, queue)
    one = tex = None
    if one_sigma:
        one = _crossover(radii, tuple(ms[1:1 + len(radii)]), ms[0], FIR_MAX_RADIUS_TUNED)
        ms = ms[1 + len(radii):]
    if per_texel:
        tex = _crossover(texel_radii, tuple(ms[1:]), ms[0], FIR_MAX_RADIUS_PER_TEXEL)
    return DirectLimits(one, tex, "measured", time.perf_counter() - start)


TUNE_STREAM = streams(TUNE_SIZE * TUNE_SIZE * 16)
"""Whether the measured blurs write with streaming stores."""


def tuning_kernels(device: Device) -> list[Any]:
    """The per-texel direct kernels :func:`measure_direct_limits` times (for
    :class:`~.opencl.Prewarm`; its recursive one is
    ``recursive_blur.pass_kernels(TUNE_STREAM)``). The one-sigma switch is measured
    only by a render that runs one-sigma blurs: the demo runs none."""
    if known_limit(device, per_texel=True) is not None:
        return []  # measured before: nothing will be timed
    direct = direct_kernels(device)
    return [direct.kernel(r, r, TUNE_STREAM, True) for r in TEXEL_RADII]


def _cache_key(device: Device) -> list[Any]:
    """What the measured switch depends on: the device, its driver, skinpipe's version."""
    d = device.cl_device
    return ["blur-switch", device.choice.candidate.label, d.driver_version, d.version,
            d.max_compute_units, __version__, TUNE_SIZE]


def _cache_path(device: Device) -> Path | None:
    folder = kind_folder("opencl")
    return None if folder is None else \
        folder / f"{entry_name('blur-switch', _cache_key(device))}.json"


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


_KINDS = {False: "max_radius", True: "max_radius_per_texel"}


_BOUNDS = {"max_radius": FIR_MAX_RADIUS_TUNED, "max_radius_per_texel": FIR_MAX_RADIUS_PER_TEXEL}


def _read_cache(device: Device) -> dict[str, int]:
    """The switch measured before on this device, each kind checked against the radii
    the kernels are built for (a record out of range is removed, and measured again)."""
    path = _cache_path(device)
    saved = None if path is None else read_json_entry(path, _cache_key(device))
    if saved is None:
        return {}
    for kind, value in saved.items():
        if kind not in _BOUNDS or not isinstance(value, int) or isinstance(value, bool) \
                or not 0 <= value <= _BOUNDS[kind]:
            reject(path, f"{kind} = {value!r} is not a radius 0-{_BOUNDS.get(kind, 0)}")
            return {}
    return saved


def known_limit(device: Device, per_texel: bool) -> int | None:
    """The switch of one kind from :data:`SWITCH_ENV` or the disk cache; None if it must
    be measured."""
    if os.environ.get(SWITCH_ENV):
        return getattr(fixed_limits(os.environ[SWITCH_ENV]), _KINDS[per_texel])
    return _read_cache(device).get(_KINDS[per_texel])


@lru_cache(maxsize=8)
def direct_limit(device: Device, per_texel: bool) -> tuple[int, str, float]:
    """(widest direct radius, source, seconds measuring) for one-sigma or per-texel
    blurs on the chosen device: :data:`SWITCH_ENV` if set, else from the disk cache,
    else measured now (that kind only, about 0.2 s) and stored beside the other."""
    known = known_limit(device, per_texel)
    if known is not None:
        return known, "fixed" if os.environ.get(SWITCH_ENV) else "cache", 0.0
    measured = measure_direct_limits(device, one_sigma=not per_texel, per_texel=per_texel)
    value = getattr(measured, _KINDS[per_texel])
    assert value is not None
    path = _cache_path(device)
    if path is not None:
        with contextlib.suppress(OSError):  # unkept, it costs a measurement a process
            write_json_entry(path, _cache_key(device),
                             {**_read_cache(device), _KINDS[per_texel]: value})
    return value, "measured", measured.seconds


def direct_limits(device: Device) -> DirectLimits | None:
    """The switch this process used on ``device``, for ``render.json`` (a kind no blur
    asked for: None; None if no blur asked at all)."""
    asked = {k: direct_limit(device, k) for k in (False, True) if k in _asked_kinds(device)}
    if not asked:
        return None
    sources = sorted({v[1] for v in asked.values()})
    return DirectLimits(asked[False][0] if False in asked else None,
                        asked[True][0] if True in asked else None, "+".join(sources),
                        sum(v[2] for v in asked.values()))


@lru_cache(maxsize=4)
def _asked_kinds(device: Device) -> set[bool]:
    """The kinds a blur has asked :func:`prefers_direct` about on this device."""
    return set()


def prefers_direct(device: Device, sigma_u: float, sigma_v: float, per_texel: bool = False,
                   limits: DirectLimits | None = None) -> bool:
    """Whether the direct blur is the faster one for these sigmas (texels; per texel: the
    widest) on this device: both radii within the switch (``limits``, else
    :func:`direct_limit` of that kind)."""
    if limits is not None:
        limit = limits.max_radius_per_texel if per_texel else limits.max_radius
        assert limit is not None, "limits without this kind"
    else:
        limit = direct_limit(device, per_texel)[0]
        _asked_kinds(device).add(per_texel)
    return max(direct_radius(sigma_u), direct_radius(sigma_v)) <= limit
