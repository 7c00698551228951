"""The OpenCL device every texture-space kernel runs on, chosen by probing every
candidate (PoCL's, Intel's CPU runtime, any GPU the machine's drivers offer) with a small
kernel that uses what skinpipe's kernels use; compiled programs are cached on disk for
every runtime; builds and kernel launches are counted for ``render.json``."""

from __future__ import annotations

import math
import mmap
import os
import threading
import time
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pyopencl as cl
from numpy.typing import NDArray

from ..errors import InputError
from .huge_pages import huge_pages_choice
from .opencl_runtimes import (
    SETUP,
    cache_root,
    note_pocl_probe,
    pocl_passed_here,
    register_vendors,
)
from .options import DEVICE_ENV

STREAM_MIN_BYTES = 16 << 20
"""Blurs of images this large write their output with streaming (non-temporal) stores:
a normal store first reads the line it writes, so a texture that will not stay in the
cache anyway is read twice (measured at 2048^2 RGBA float32, 64 MiB: the one-sigma
recursive blur 45-47 -> 34-36 ms, the direct blur at sigma 1 17 -> 10 ms). Smaller
images are left in the cache for the kernel that reads them next."""


def streams(nbytes: int) -> bool:
    """Whether a blur writing an image of ``nbytes`` uses streaming stores."""
    return nbytes >= STREAM_MIN_BYTES
HUGE_PAGE_MIN_BYTES = 4 << 20
"""Work buffers this large live in host memory backed by 2 MiB pages on a CPU device
(:func:`device_buffer`)."""
_HUGE_PAGE = 2 << 20
STORE_MACRO = r"""
#if STREAM && NT_STORE
#define STORE(v, p) __builtin_nontemporal_store((v), (p))
#else
#define STORE(v, p) (*(p) = (v))
#endif
"""

HALF_BITS = r"""
// Half floats by their bits, as numpy's float16 <-> float32 (round to nearest even):
// vload_half and vstore_half are calls on PoCL, not inlined (with vload_half the
// diffusion's level-0 batches at texture 4096 took 120 ms, 70 with float32 weights).
// half_bits_to_float (finite halves): the exponent and mantissa shifted into a float's
// place, the exponent rebased from half's bias (15) to float's (127); a subnormal half
// (exponent 0, m 2^-24) read as the normal number 2^-14 (1 + m 2^-10), less 2^-14: both
// exact.
__attribute__((always_inline)) inline float half_bits_to_float(ushort h)
{
    const uint b = (uint)(h & 0x7fff) << 13;
    const float v = (h & 0x7c00) ? as_float(b + (112u << 23))
                                 : as_float(b + (113u << 23)) - 6.103515625e-05f;
    return (h & 0x8000) ? -v : v;
}
// float_to_half_bits (finite floats below 65520, half's largest after rounding; after
// Giesen's float_to_half_fast3_rtne): below 2^-14 the float's addition to 0.5 (whose
// ulp is 2^-24, a subnormal half's step) rounds to nearest even, and its bits less 0.5's
// are the half's; above, the exponent rebased and the 13 dropped bits rounded by adding
// 0xfff plus the kept mantissa's lowest bit (ties to even).
__attribute__((always_inline)) inline ushort float_to_half_bits(float f)
{
    const uint sign = as_uint(f) & 0x80000000u, u = as_uint(f) ^ sign;
    const uint small = as_uint(as_float(u) + 0.5f) - as_uint(0.5f);
    const uint normal = (u + 0xc8000fffu + ((u >> 13) & 1u)) >> 13;  // 0xc8...: -112 << 23
    return (ushort)((u < (113u << 23) ? small : normal) | (sign >> 16));
}
"""
"""OpenCL C: ``half_bits_to_float(ushort)`` and ``float_to_half_bits(float)``, half floats
kept as ``ushort`` bits, converted as numpy's float16 does, without PoCL's calls."""


MIN_LOCAL_MEM_BYTES = 32 << 10
"""Local memory a device needs: the direct blur's ring (20 KiB). The recursive blur's
rows (64 B a texel of a row) go to a global buffer where they do not fit (NVIDIA's GPUs
offer OpenCL 48 KiB, 768 texels)."""
PROBE_ITEMS = 256
_T = TypeVar("_T", bound=Callable[..., Any])
_DEVICE_CACHES: list[Any] = []


def device_cache(maxsize: int = 1) -> Callable[[_T], _T]:
    """``lru_cache`` for what belongs to the chosen device (contexts, programs, buffers,
    tuned switches): cleared together when another device is chosen."""
    def wrap(fn: _T) -> _T:
        cached = lru_cache(maxsize=maxsize)(fn)
        _DEVICE_CACHES.append(cached)
        return cached  # type: ignore[return-value]
    return wrap


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


@dataclass(frozen=True)
class Candidate:
    """One OpenCL device as the ICD loader lists it."""

    platform: str
    name: str
    kind: str
    """"cpu", "gpu" or "other"."""
    platform_index: int
    device_index: int

    @property
    def label(self) -> str:
        return f"{self.platform}: {self.name}"

    @property
    def runtime(self) -> str:
        """Short id of the runtime and kind, e.g. ``pocl-cpu``, ``intel-cpu``."""
        p = self.platform.lower()
        vendor = ("pocl" if "portable computing" in p or "pocl" in p else
                  next((v for v in RUNTIME_VENDORS if v in p),
                       "".join(c for c in p.split()[0] if c.isalnum()) or "cl"))
        return f"{vendor}-{self.kind}"


RUNTIME_VENDORS = ("pocl", "intel", "nvidia", "amd", "rusticl", "clover", "apple")
"""Runtime vendors a device spec names as runtimes (``intel``: Intel's runtime, never a
device whose name says Intel)."""


@dataclass
class DeviceChoice:
    """The device chosen for this process and every device tried (reason None: passed
    the probe; ``not tried``: the chosen one came first)."""

    spec: str
    device: Any
    candidate: Candidate
    nontemporal_stores: bool
    tried: list[tuple[Candidate, str | None]] = field(default_factory=list)

    def summary(self) -> dict[str, Any]:
        return {"device": self.candidate.label, "runtime": self.candidate.runtime,
                "spec": self.spec, "nontemporal_stores": self.nontemporal_stores,
                "tried": {c.label: reason or "passed" for c, reason in self.tried},
                "runtime_notes": list(SETUP.notes)}


LEAN_SPECS = ("auto", "cpu", "gpu", "pocl", "pocl-cpu")
"""Device specs that do without Intel's runtime once PoCL has passed the probe here:
they rank PoCL's CPU device ahead of it (see :func:`order_candidates`)."""


def candidates(all_runtimes: bool = False, spec: str | None = None
               ) -> list[tuple[Candidate, Any]]:
    """Every device of every platform, with its pyopencl object; ``[]`` when the loader
    has no platform at all. At the process's first platform query the runtimes are
    registered (:func:`~.opencl_runtimes.register_vendors`): Intel's CPU runtime with
    ``all_runtimes`` (every device is wanted: ``skinpipe env``, the tests), for a device
    ``spec`` (default :func:`device_spec`) outside :data:`LEAN_SPECS`, or where PoCL has
    not passed the probe on this CPU before; later queries list what the first one
    registered."""
    spec = (device_spec() if spec is None else spec).strip().lower()
    wants_intel = all_runtimes or spec not in LEAN_SPECS
    if SETUP.settled and SETUP.intel_left_out and wants_intel:
        SETUP.note(f"Intel CPU runtime: left out at this process's first OpenCL query, "
                   f"before device '{spec}' was asked for (ask for it before any OpenCL "
                   f"work)")
    register_vendors(wants_intel or not pocl_passed_here())
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # ocl-icd raises PLATFORM_NOT_FOUND_KHR with no ICD
        return []
    out = []
    for pi, platform in enumerate(platforms):
        try:
            devices = platform.get_devices()
        except cl.Error:
            continue
        for di, d in enumerate(devices):
            kind = ("cpu" if d.type & cl.device_type.CPU else
                    "gpu" if d.type & cl.device_type.GPU else "other")
            out.append((Candidate(platform.name.strip(), d.name.strip(), kind, pi, di), d))
    return out


def order_candidates(found: Sequence[tuple[Candidate, Any]], spec: str
                     ) -> list[tuple[Candidate, Any]]:
    """The devices to try for ``spec``, in order (see :data:`DEVICE_HELP`)."""
    s = spec.strip().lower()
    rank_kind = {"cpu": 0, "gpu": 1, "other": 2}
    if s == "gpu":
        rank_kind = {"gpu": 0, "cpu": 1, "other": 2}

    def rank(item: tuple[Candidate, Any]) -> tuple[int, int, int, int]:
        c = item[0]
        return (rank_kind[c.kind], 0 if c.runtime.startswith("pocl") else 1,
                c.platform_index, c.device_index)

    if s in ("auto", "gpu"):
        pool = list(found)
    elif s == "cpu":
        pool = [f for f in found if f[0].kind == "cpu"]
    else:
        # a runtime's id or vendor ("intel-cpu", "intel") names that runtime only: on an
        # Intel CPU PoCL's device is "pthread-Intel(R) Xeon ..." too
        pool = [f for f in found if s in (f[0].runtime, f[0].runtime.split("-")[0])]
        if not pool and s.split("-")[0] not in RUNTIME_VENDORS:
            pool = [f for f in found if s in f[0].label.lower() or s in f[0].runtime]
    return sorted(pool, key=rank)


_PROBE_SOURCE = r"""
__kernel void probe(__global const float4 *src, __global float4 *dst,
                    volatile __global int *peak, __local float4 *tile) {
    const int l = get_local_id(0), n = get_local_size(0), g = get_global_id(0);
    tile[l] = src[g];
    barrier(CLK_LOCAL_MEM_FENCE);
    float4 v = tile[n - 1 - l] * 2.0f;
#if NT_STORE
    __builtin_nontemporal_store(v, dst + g);
#else
    dst[g] = v;
#endif
    atomic_max(peak, (int)src[g].x);
}
"""


def _first_error_line(exc: BaseException) -> str:
    """The line of a build log or exception that says what failed."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in lines:
        if "error" in ln.lower() and "build_program_failure" not in ln.lower():
            return ln[:200]
    return (lines[0] if lines else type(exc).__name__)[:200]


def probe(device: Any, nt_store: bool = True) -> str | None:
    """None if ``device`` builds and runs the probe kernel right (local memory, a barrier,
    atomics, ``USE_HOST_PTR`` buffers, and with ``nt_store`` the streaming-store builtin),
    else why not (one line)."""
    try:
        if int(device.local_mem_size) < MIN_LOCAL_MEM_BYTES:
            return (f"local memory {int(device.local_mem_size) >> 10} KiB < "
                    f"{MIN_LOCAL_MEM_BYTES >> 10} KiB")
        local = int(min(64, device.max_work_group_size))
        ctx = cl.Context([device])
        queue = cl.CommandQueue(ctx)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", cl.CompilerWarning)
            program = cl.Program(ctx, _PROBE_SOURCE).build(
                options=[f"-DNT_STORE={int(nt_store)}"], cache_dir=str(program_cache_dir()))
        src = np.arange(PROBE_ITEMS * 4, dtype=np.float32).reshape(-1, 4)
        dst = np.zeros_like(src)
        peak = np.full(1, -1, np.int32)
        mf = cl.mem_flags
        b_src = cl.Buffer(ctx, mf.READ_ONLY | mf.USE_HOST_PTR, hostbuf=src)
        b_dst = cl.Buffer(ctx, mf.READ_WRITE | mf.USE_HOST_PTR, hostbuf=dst)
        b_peak = cl.Buffer(ctx, mf.READ_WRITE | mf.COPY_HOST_PTR, hostbuf=peak)
        program.probe(queue, (PROBE_ITEMS,), (local,), b_src, b_dst, b_peak,
                      cl.LocalMemory(16 * local))
        mapped, _ = cl.enqueue_map_buffer(queue, b_dst, cl.map_flags.READ, 0, dst.shape,
                                          dst.dtype)
        got = np.array(mapped)
        mapped.base.release(queue)
        cl.enqueue_copy(queue, peak, b_peak)
        queue.finish()
    except Exception as exc:  # a runtime can fail anywhere: that is what the probe asks
        return f"{'build' if 'build' in str(exc).lower() else 'run'} failed: " \
               f"{_first_error_line(exc)}"
    groups = src.reshape(-1, local, 4)
    want = (groups[:, ::-1] * 2.0).reshape(-1, 4)
    if not np.array_equal(got, want):
        return f"wrong results ({int((got != want).any(axis=1).sum())} of {PROBE_ITEMS} items)"
    if int(peak[0]) != int(src[:, 0].max()):
        return f"atomic_max gave {int(peak[0])}, expected {int(src[:, 0].max())}"
    return None


def choose_device(spec: str, found: Sequence[tuple[Candidate, Any]] | None = None,
                  probe_fn: Callable[..., str | None] = probe,
                  probe_all: bool = False) -> DeviceChoice:
    """The first device for ``spec`` that passes :func:`probe` (``probe_all``: every
    device is probed, for the report of ``skinpipe env``); an :class:`InputError`
    naming every device tried and why it failed when none does."""
    real = found is None
    found = candidates(probe_all, spec) if found is None else list(found)
    ordered = order_candidates(found, spec)
    tried: list[tuple[Candidate, str | None]] = []
    chosen: tuple[Candidate, Any, bool] | None = None
    for cand, device in ordered:
        if chosen is not None and not probe_all:
            tried.append((cand, "not tried (an earlier device passed)"))
            continue
        reason = probe_fn(device, True)
        nt = reason is None
        if reason is not None and probe_fn(device, False) is None:
            reason = None  # it runs everything but streaming stores: plain stores then
        tried.append((cand, reason if reason or chosen is None else
                      "passed (an earlier device was chosen)"))
        if real and cand.runtime == "pocl-cpu":
            note_pocl_probe(reason is None)  # whether the next process needs Intel's
        if reason is None and chosen is None:
            chosen = (cand, device, nt)
    if chosen is None:
        if real and SETUP.intel_left_out and any(
                c.runtime == "pocl-cpu" and r is not None for c, r in tried):
            SETUP.note("PoCL fails here now: the next process loads Intel's runtime")
        raise InputError(no_device_message(spec, found, tried))
    tried += [(c, f"not matched by '{spec}'") for c, _ in found
              if all(c != o for o, _ in ordered)]
    return DeviceChoice(spec, chosen[1], chosen[0], chosen[2], tried)


def no_device_message(spec: str, found: Sequence[tuple[Candidate, Any]],
                      tried: Sequence[tuple[Candidate, str | None]]) -> str:
    if not found:
        head = "no OpenCL device found"
    elif not tried:
        head = (f"no OpenCL device matches '{spec}' (have: "
                + ", ".join(c.label for c, _ in found) + ")")
    else:
        head = f"no OpenCL device passed skinpipe's probe (device '{spec}'): " + "; ".join(
            f"{c.label}: {r}" for c, r in tried)
    notes = "; ".join(SETUP.notes)
    return (f"{head}. Install a CPU runtime (pip install 'skinpipe[intel-cpu]': Intel's, "
            f"for CPUs PoCL cannot build for) or a GPU driver's OpenCL ICD, or choose another "
            f"with --device / ${DEVICE_ENV}" + (f" ({notes})" if notes else ""))


_preference: str | None = None


def device_spec() -> str:
    """The device asked for: :func:`set_device` if called, else ``$SKINPIPE_OPENCL_DEVICE``,
    else ``auto``."""
    return (_preference or os.environ.get(DEVICE_ENV) or "auto").strip() or "auto"


def set_device(spec: str | None) -> None:
    """Ask for another device (None: back to the environment / auto). Every
    device-bound cache (:func:`device_cache`) is cleared when the choice changes, so
    buffers and programs of the old device are never mixed with the new one."""
    global _preference
    before = device_spec()
    _preference = spec
    if device_spec() != before:
        for cached in _DEVICE_CACHES:
            cached.cache_clear()


_CHOICE_LOCK = threading.RLock()
"""One thread probes and makes the context; the others wait for it (a :class:`Prewarm`
starts while the render builds its BVH)."""


@device_cache()
def _device_choice() -> DeviceChoice:
    return choose_device(device_spec())


def device_choice() -> DeviceChoice:
    """The device of this process (probed once)."""
    with _CHOICE_LOCK:
        return _device_choice()


@device_cache()
def _cl_context() -> tuple[Any, Any]:
    ctx = cl.Context([device_choice().device])
    return ctx, cl.CommandQueue(ctx)


def cl_context() -> tuple[Any, Any]:
    """(context, in-order queue) on the chosen device, made once per device."""
    with _CHOICE_LOCK:
        return _cl_context()


def program_cache_dir() -> Path:
    """Where built programs are kept (pyopencl's binary cache, for every runtime)."""
    return cache_root() / "opencl" / "programs"


def cache_is_cold() -> bool:
    """Whether nothing has been compiled into skinpipe's disk caches yet (pyopencl's
    binaries, which it keeps only for runtimes without a cache of their own, and
    PoCL's kernels): a cheap sign of a first render, which asks nothing of the
    device."""
    for folder in (program_cache_dir(), cache_root() / "pocl"):
        try:
            if any(folder.iterdir()):
                return False
        except OSError:
            continue
    return True


@dataclass
class KernelLedger:
    """Program builds (count, seconds) and kernel launches by name, for this process:
    a render reports its difference (:meth:`since`)."""

    builds: int = 0
    build_seconds: float = 0.0
    launches: Counter[str] = field(default_factory=Counter)
    prewarmed: int = 0
    """Kernels made by a :class:`Prewarm` (built, and on PoCL compiled, ahead of use)."""
    prewarm_seconds: float = 0.0
    """Wall seconds the prewarms ran (beside the render's own work)."""

    def copy(self) -> KernelLedger:
        return KernelLedger(self.builds, self.build_seconds, Counter(self.launches),
                            self.prewarmed, self.prewarm_seconds)

    def since(self, before: KernelLedger) -> dict[str, Any]:
        launches = self.launches - before.launches
        return {"programs_built": self.builds - before.builds,
                "build_seconds": round(self.build_seconds - before.build_seconds, 4),
                "kernels_prewarmed": self.prewarmed - before.prewarmed,
                "prewarm_seconds": round(self.prewarm_seconds - before.prewarm_seconds, 4),
                "kernel_launches": dict(sorted(launches.items()))}


LEDGER = KernelLedger()


_BUILD_LOCK = threading.Lock()


@device_cache()
def _programs() -> dict[tuple[str, tuple[str, ...]], Future[Any]]:
    """Programs of this process by (source, options), built or being built: a program
    that :func:`prewarm` is building is waited for, not built twice."""
    return {}


def build(source: str, options: list[str] | None = None) -> Any:
    """A program for the shared context, built once per process (callers may call
    again), from the disk cache when it was built before; ``NT_STORE`` says whether
    streaming stores work. Safe to call from several threads."""
    key = (source, tuple(options or ()))
    with _BUILD_LOCK:
        pending = _programs().get(key)
        if pending is None:
            pending = _programs()[key] = Future()
            mine = True
        else:
            mine = False
    if not mine:
        return pending.result()
    try:
        program = _build_now(source, options)
    except BaseException as exc:
        with _BUILD_LOCK:
            _programs().pop(key, None)  # a later call tries again and sees the error
        pending.set_exception(exc)
        raise
    pending.set_result(program)
    return program


def _build_now(source: str, options: list[str] | None) -> Any:
    ctx, _ = cl_context()
    # argument info lets Kernel.warm fill a launch of any kernel
    opts = [*(options or []), f"-DNT_STORE={int(device_choice().nontemporal_stores)}",
            "-cl-kernel-arg-info"]
    start = time.perf_counter()
    with warnings.catch_warnings():
        # Intel's runtime writes a build log for every program, errors or not
        warnings.simplefilter("ignore", cl.CompilerWarning)
        program = cl.Program(ctx, source).build(options=opts,
                                                cache_dir=str(program_cache_dir()))
    with _BUILD_LOCK:
        LEDGER.builds += 1
        LEDGER.build_seconds += time.perf_counter() - start
    return program


FIXED_LOCAL_SIZES = {1: (256,), 2: (32, 8)}
"""Work-group shape of launches that leave it to the runtime (``local_size`` None): the
global size is padded to a multiple and the kernels test their bounds. Left to itself,
PoCL picks a shape from the global size and compiles the kernel again for each one (its
kernel cache is keyed by the shape): a push-pull pyramid of 10 levels cost 20
compilations of two kernels on a cold cache, and every new texture size more."""


def fixed_local_size(global_size: tuple[int, ...], limit: int
                     ) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(padded global size, local size) for :data:`FIXED_LOCAL_SIZES`, the local size
    halved (first axis first) until it fits the kernel's ``limit`` of work items."""
    local = list(FIXED_LOCAL_SIZES[len(global_size)])
    while math.prod(local) > max(1, limit):
        k = 0 if local[0] > 1 else 1
        local[k] //= 2
    padded = tuple(-(-int(g) // n) * n for g, n in zip(global_size, local, strict=True))
    return padded, tuple(local)


_SCALAR_TYPES = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16,
                 "int": np.int32, "uint": np.uint32, "long": np.int64, "ulong": np.uint64,
                 "float": np.float32, "double": np.float64}


class Kernel:
    """A kernel of a built program whose launches are counted in :data:`LEDGER`.

    ``shape`` is its work-group shape: a tuple (the launches give it) or the number of
    dimensions of launches that give none: those run on :func:`fixed_local_size`, on a
    grid padded past the global size, so such a kernel must test its bounds (each of
    skinpipe's does: ``tests/render/test_opencl.py`` reads every kernel source for it)."""

    __slots__ = ("_kernel", "_limit", "_program", "name", "shape")

    def __init__(self, program: Any, name: str, shape: int | tuple[int, ...] = 2) -> None:
        self._program = program
        self._kernel = cl.Kernel(program, name)
        self.name = name
        self.shape = shape
        self._limit = self._kernel.get_work_group_info(
            cl.kernel_work_group_info.WORK_GROUP_SIZE, device_choice().device)

    def __call__(self, queue: Any, global_size: tuple[int, ...],
                 local_size: tuple[int, ...] | None, *args: Any, **kwargs: Any) -> Any:
        LEDGER.launches[self.name] += 1
        if local_size is None:
            global_size, local_size = fixed_local_size(tuple(global_size), self._limit)
        return self._kernel(queue, global_size, local_size, *args, **kwargs)

    def warm(self, queue: Any) -> None:
        """Launch one work group of the kernel's shape with every buffer a dummy and
        every number 0 (each of skinpipe's kernels returns at its bounds test), on a
        kernel object of its own (arguments belong to the object): PoCL compiles a
        kernel for its work-group shape at the first launch, and that is then done."""
        kernel = cl.Kernel(self._program, self.name)
        ctx = queue.context
        args: list[Any] = []
        aq = cl.kernel_arg_address_qualifier
        for i in range(kernel.num_args):
            where = kernel.get_arg_info(i, cl.kernel_arg_info.ADDRESS_QUALIFIER)
            if where == aq.LOCAL:
                args.append(cl.LocalMemory(64))
            elif where in (aq.GLOBAL, aq.CONSTANT):
                args.append(cl.Buffer(ctx, cl.mem_flags.READ_WRITE, 256))
            else:
                type_name = kernel.get_arg_info(i, cl.kernel_arg_info.TYPE_NAME)
                args.append(_SCALAR_TYPES[type_name.strip().rstrip("*")](0))
        local = self.shape if isinstance(self.shape, tuple) else \
            fixed_local_size((1,) * self.shape, self._limit)[1]
        kernel(queue, local, local, *args)
        queue.finish()


def jit_at_first_launch() -> bool:
    """Whether the device compiles kernels at their first launch (PoCL) rather than when
    their program is built (Intel's runtime, GPU drivers)."""
    return _on_pocl()


def _on_pocl() -> bool:
    return device_choice().candidate.runtime.startswith("pocl")


class Prewarm:
    """Programs built, and on PoCL kernels compiled, on a background thread ahead of
    their first use, while the render's host work (texture maps, Embree's rays, numpy)
    goes on: a cold first render otherwise waits for each compilation in turn.

    ``steps`` run in order; each returns the kernels it made (built through the
    modules' own cached builders, so the render finds them there) or None. A step that
    fails is left for the render to meet again where its error is reported."""

    def __init__(self, steps: Sequence[Callable[[], Any]]) -> None:
        cl_context()  # the device is chosen before the thread starts
        self.seconds = 0.0
        self.kernels = 0
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(list(steps),),
                                        name="skinpipe-prewarm", daemon=True)
        self._thread.start()

    def _run(self, steps: list[Callable[[], Any]]) -> None:
        start = time.perf_counter()
        try:
            ctx, _ = cl_context()
            queue = cl.CommandQueue(ctx)
            jit = jit_at_first_launch()
            for step in steps:
                try:
                    made = step()
                    if isinstance(made, dict):
                        made = list(made.values())
                    elif not isinstance(made, (list, tuple)):
                        made = [made]
                    for kernel in made:
                        if isinstance(kernel, Kernel):
                            self.kernels += 1
                            if jit:
                                kernel.warm(queue)
                except Exception:  # the render meets it again, where it is reported
                    continue
        except Exception:  # the render reports a device that fails itself
            pass
        finally:
            self.seconds = time.perf_counter() - start
            with _BUILD_LOCK:
                LEDGER.prewarmed += self.kernels
                LEDGER.prewarm_seconds += self.seconds
            self._done.set()

    def wait(self) -> None:
        """Until every step has run (before timing kernels, which must not share the
        host with compilations)."""
        self._done.wait()


_ACTIVE: list[Prewarm] = []


def start_prewarm(steps: Sequence[Callable[[], Any]]) -> Prewarm:
    """A :class:`Prewarm` of ``steps``, which :func:`wait_for_prewarm` waits for."""
    _ACTIVE[:] = [pre for pre in _ACTIVE if not pre._done.is_set()]
    _ACTIVE.append(Prewarm(steps))
    return _ACTIVE[-1]


def wait_for_prewarm() -> None:
    """Until every started :class:`Prewarm` is done."""
    for pre in _ACTIVE:
        pre.wait()


@device_cache()
def _host_memory_device() -> bool:
    """Whether the device runs on this machine's memory (a CPU device)."""
    return device_choice().candidate.kind == "cpu"

def device_buffer(size_or_contents: int | NDArray[Any]) -> Any:
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
    if huge_pages_choice().use:
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
    ctx, _ = cl_context()
    data = array if array.size else np.zeros(1, array.dtype)
    how = cl.mem_flags.USE_HOST_PTR if _host_memory_device() else cl.mem_flags.COPY_HOST_PTR
    return cl.Buffer(ctx, access | how, hostbuf=data)


def host_buffer(array: NDArray[Any]) -> Any:
    """A read-only device buffer over ``array`` (made C-contiguous): on a CPU device the
    array's own memory (no second copy of, say, 100 MB of region weights; pyopencl
    keeps the array alive as long as the buffer, and nothing may write to it
    meanwhile), elsewhere a copy."""
    return _over_host(np.ascontiguousarray(array), cl.mem_flags.READ_ONLY)


def host_output(array: NDArray[Any]) -> Any:
    """A device buffer holding ``array``'s values that kernels write the array's new
    contents into: on a CPU device the array's own memory (no copy either way;
    :func:`read_output` makes the array current), elsewhere a copy."""
    if not array.flags.c_contiguous:
        raise InputError("host_output: the array must be C-contiguous")
    return _over_host(array, cl.mem_flags.READ_WRITE)


def run_on_host_arrays(kernel: Any, queue: Any, global_size: tuple[int, ...],
                       args: Sequence[Any], outputs: Sequence[NDArray[Any]]) -> None:
    """Launch ``kernel`` over ``global_size`` with ``args`` and then ``outputs`` as its
    arguments, and wait for it. Each numpy array among ``args`` is read through
    :func:`host_buffer` (in place on a CPU device) and each of ``outputs`` written
    through :func:`host_output`, current on return. The buffers are held until the
    kernel is done: a buffer over a host array lets the array go with it, while the
    kernel may still read it."""
    held = [host_buffer(a) if isinstance(a, np.ndarray) else a for a in args]
    written = [host_output(a) for a in outputs]
    kernel(queue, global_size, None, *held, *written)
    for buffer, array in zip(written, outputs, strict=True):
        read_output(queue, buffer, array)


def read_output(queue: Any, buffer: Any, array: NDArray[Any]) -> None:
    """Bring ``array`` up to date with the :func:`host_output` buffer over it: a map and
    unmap of the memory in place on a CPU device, a copy elsewhere (waits for the queue).
    An empty array has nothing to bring (OpenCL refuses to map zero bytes)."""
    if array.size == 0:
        queue.finish()
        return
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
