"""The OpenCL device every texture-space kernel runs on, chosen by probing every
candidate (PoCL's, Intel's CPU runtime, any GPU the machine's drivers offer) with a small
kernel that uses what skinpipe's kernels use; the first that passes is used."""

from __future__ import annotations

import atexit
import os
import threading
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np
import pyopencl as cl

from ...errors import InputError
from ..cache import GuardedTree, cache_root
from ..options import DEVICE_ENV
from .runtimes import (
    SETUP,
    note_pocl_probe,
    pocl_passed_here,
    register_vendors,
)
from .sources import cl_source

MIN_LOCAL_MEM_BYTES = 32 << 10
"""Local memory a device needs: the direct blur's ring (20 KiB). The recursive blur's
rows (64 B a texel of a row) go to a global buffer where they do not fit (NVIDIA's GPUs
offer OpenCL 48 KiB, 768 texels)."""
PROBE_ITEMS = 256
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


_PROBE_SOURCE = cl_source(__package__, "probe.cl")


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


@lru_cache(maxsize=1)
def program_cache_dir() -> Path:
    """Where built programs are kept (pyopencl's binary cache, which it fills for
    runtimes without a cache of their own), checked before its first use."""
    tree = GuardedTree(cache_root() / "opencl" / "programs", "OpenCL programs")
    atexit.register(tree.close)
    return tree.open()


def device_spec() -> str:
    """The device asked for by the environment: ``$SKINPIPE_OPENCL_DEVICE``, else
    ``auto``."""
    return (os.environ.get(DEVICE_ENV) or "auto").strip() or "auto"


class Device:
    """The OpenCL device a render runs on: the probe's choice, a context and an in-order
    queue on it, and the programs built for it. Made by :func:`open_device` and passed
    down to every step that launches a kernel or makes a buffer; what is built or kept
    for a device (kernels, coefficient buffers, a tuned blur switch) is cached by the
    device object, so two devices in one process never share one."""

    __slots__ = ("choice", "context", "programs", "queue")

    def __init__(self, choice: DeviceChoice) -> None:
        self.choice = choice
        self.context = cl.Context([choice.device])
        self.queue = cl.CommandQueue(self.context)
        self.programs: dict[tuple[str, tuple[str, ...]], Any] = {}
        """Programs by (source, options), built or being built (see
        :func:`~.programs.build`)."""

    @property
    def cl_device(self) -> Any:
        """The pyopencl device."""
        return self.choice.device

    @property
    def runtime(self) -> str:
        return self.choice.candidate.runtime

    @property
    def on_host_memory(self) -> bool:
        """Whether the device runs on this machine's memory (a CPU device)."""
        return self.choice.candidate.kind == "cpu"

    @property
    def nontemporal_stores(self) -> bool:
        return self.choice.nontemporal_stores

    @property
    def has_doubles(self) -> bool:
        return "cl_khr_fp64" in self.choice.device.extensions

    @property
    def jit_at_first_launch(self) -> bool:
        """Whether the device compiles kernels at their first launch (PoCL) rather than
        when their program is built (Intel's runtime, GPU drivers)."""
        return self.runtime.startswith("pocl")

    def __repr__(self) -> str:
        return f"Device({self.choice.candidate.label!r}, spec={self.choice.spec!r})"


def or_default(device: Device | None) -> Device:
    """``device``, or where None the environment's (:func:`open_device` of
    :func:`device_spec`): for scripts and tests calling one step; a render passes its
    own."""
    return open_device() if device is None else device


_OPEN_LOCK = threading.Lock()
_OPENED: dict[str, Device] = {}


def open_device(spec: str | None = None) -> Device:
    """The device for ``spec`` (None or empty: :func:`device_spec`), probed at the first request
    for that spec in this process and then the same object: its programs and kernels
    stay built for the next render. An :class:`InputError` naming every device tried
    when none passes."""
    key = (spec or device_spec()).strip().lower() or "auto"
    with _OPEN_LOCK:
        device = _OPENED.get(key)
        if device is None:
            device = _OPENED[key] = Device(choose_device(key))
        return device
