"""Programs built for the chosen device (kept on disk by pyopencl's binary cache and
PoCL's kernel cache), kernels launched on fixed work-group shapes and counted for
``render.json``, and a background thread that builds ahead what a render will need."""

from __future__ import annotations

import math
import threading
import time
import warnings
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pyopencl as cl

from .choice import Device, program_cache_dir
from .sources import cl_source

STORE_MACRO = cl_source(__package__, "streaming_store.cl")

HALF_BITS = cl_source(__package__, "half_bits.cl")
"""OpenCL C: ``half_bits_to_float(ushort)`` and ``float_to_half_bits(float)``, half floats
kept as ``ushort`` bits, converted as numpy's float16 does, without PoCL's calls."""


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


def build(device: Device, source: str, options: list[str] | None = None) -> Any:
    """A program for ``device``, built once per device (callers may call again; one
    that a :class:`Prewarm` is building is waited for, not built twice), from the disk
    cache when it was built before; ``NT_STORE`` says whether streaming stores work.
    Safe to call from several threads."""
    key = (source, tuple(options or ()))
    with _BUILD_LOCK:
        pending = device.programs.get(key)
        if pending is None:
            pending = device.programs[key] = Future()
            mine = True
        else:
            mine = False
    if not mine:
        return pending.result()
    try:
        program = _build_now(device, source, options)
    except BaseException as exc:
        with _BUILD_LOCK:
            device.programs.pop(key, None)  # a later call tries again and sees the error
        pending.set_exception(exc)
        raise
    pending.set_result(program)
    return program


def _build_now(device: Device, source: str, options: list[str] | None) -> Any:
    # argument info lets Kernel.warm fill a launch of any kernel. Denormals flushed to
    # zero: a recursive blur's tail decaying across a layout's empty margins runs
    # through subnormal floats, which x86 cores handle in microcode, many times slower
    # (the 2048^2 blur at the copy floor with them flushed: docs/benchmarks.md)
    opts = [*(options or []), f"-DNT_STORE={int(device.nontemporal_stores)}",
            "-cl-kernel-arg-info", "-cl-denorms-are-zero"]
    start = time.perf_counter()
    with warnings.catch_warnings():
        # Intel's runtime writes a build log for every program, errors or not
        warnings.simplefilter("ignore", cl.CompilerWarning)
        program = cl.Program(device.context, source).build(options=opts,
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
    skinpipe's does: ``tests/render/device/test_opencl.py`` reads every kernel source for it)."""

    __slots__ = ("_kernel", "_limit", "_program", "name", "shape")

    def __init__(self, program: Any, name: str, shape: int | tuple[int, ...] = 2) -> None:
        self._program = program
        self._kernel = cl.Kernel(program, name)
        self.name = name
        self.shape = shape
        self._limit = self._kernel.get_work_group_info(
            cl.kernel_work_group_info.WORK_GROUP_SIZE, program.devices[0])

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


class Prewarm:
    """Programs built, and on PoCL kernels compiled, on a background thread ahead of
    their first use, while the render's host work (texture maps, Embree's rays, numpy)
    goes on: a cold first render otherwise waits for each compilation in turn.

    ``steps`` run in order; each returns the kernels it made (built through the
    modules' own cached builders, so the render finds them there) or None. A step that
    fails is left for the render to meet again where its error is reported."""

    def __init__(self, device: Device, steps: Sequence[Callable[[], Any]]) -> None:
        self.device = device
        self.seconds = 0.0
        self.kernels = 0
        self._done = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(list(steps),),
                                        name="skinpipe-prewarm", daemon=True)
        self._thread.start()

    def _run(self, steps: list[Callable[[], Any]]) -> None:
        start = time.perf_counter()
        try:
            queue = cl.CommandQueue(self.device.context)
            jit = self.device.jit_at_first_launch
            for step in steps:
                if self._stop.is_set():
                    break
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


def start_prewarm(device: Device, steps: Sequence[Callable[[], Any]]) -> Prewarm:
    """A :class:`Prewarm` of ``steps`` on ``device``, which :func:`wait_for_prewarm`
    waits for."""
    _ACTIVE[:] = [pre for pre in _ACTIVE if not pre._done.is_set()]
    _ACTIVE.append(Prewarm(device, steps))
    return _ACTIVE[-1]


def stop_prewarm() -> None:
    """Let every :class:`Prewarm` end after the step it is in, and wait for it: a process
    must not end while a compiler runs on another thread (the runtime's destructors
    would run under it: "terminate called without an active exception")."""
    for pre in _ACTIVE:
        pre._stop.set()
    for pre in _ACTIVE:
        pre.wait()


def wait_for_prewarm() -> None:
    """Until every started :class:`Prewarm` is done."""
    for pre in _ACTIVE:
        pre.wait()
