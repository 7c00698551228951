"""OpenCL device choice: candidate order, the probe on every real device, the fallback
when a runtime cannot build (PoCL 3.0 on a CPU newer than its LLVM), the error when no
device works, the runtimes' registration with the ICD loader, and the kernel ledger."""

from __future__ import annotations

import os
import subprocess
import sys
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.device import choice, memory, programs
from skinpipe.render.device.choice import Candidate, choose_device, order_candidates

POCL = Candidate("Portable Computing Language", "pthread-AMD EPYC", "cpu", 1, 0)
INTEL = Candidate("Intel(R) OpenCL", "AMD EPYC", "cpu", 0, 0)
GPU = Candidate("NVIDIA CUDA", "NVIDIA H200", "gpu", 2, 0)
FOUND = [(INTEL, "intel"), (GPU, "gpu"), (POCL, "pocl")]
ZEN5 = "build failed: error: unknown target CPU 'generic'"


def _intel_installed() -> bool:
    try:
        metadata.distribution("intel-opencl-rt")
    except metadata.PackageNotFoundError:
        return False
    return True


def _order(spec: str) -> list[str]:
    return [c.runtime for c, _ in order_candidates(FOUND, spec)]


def test_candidate_order_for_each_spec() -> None:
    assert _order("auto") == ["pocl-cpu", "intel-cpu", "nvidia-gpu"]
    assert _order("gpu") == ["nvidia-gpu", "pocl-cpu", "intel-cpu"]
    assert _order("cpu") == ["pocl-cpu", "intel-cpu"]
    assert _order("intel") == ["intel-cpu"]
    assert _order("pocl") == ["pocl-cpu"]
    assert _order("H200") == ["nvidia-gpu"]
    assert _order("nothing-like-it") == []


def test_a_runtime_name_picks_that_runtime_on_its_vendors_cpu() -> None:
    """On an Intel CPU PoCL's device name contains "Intel" too: `intel` and `intel-cpu`
    name Intel's runtime, not PoCL (`intel` picked PoCL before); other text still
    matches names."""
    pocl = Candidate("Portable Computing Language", "pthread-Intel(R) Xeon(R) Processor",
                     "cpu", 0, 0)
    intel = Candidate("Intel(R) OpenCL", "Intel(R) Xeon(R) Processor", "cpu", 1, 0)
    found = [(pocl, "pocl"), (intel, "intel")]
    for spec in ("intel", "intel-cpu", "INTEL"):
        assert [c.runtime for c, _ in order_candidates(found, spec)] == ["intel-cpu"], spec
    assert [c.runtime for c, _ in order_candidates(found, "xeon")] == ["pocl-cpu",
                                                                       "intel-cpu"]
    # Intel's runtime not registered (left out after PoCL passed here): `intel` finds
    # nothing rather than PoCL's "pthread-Intel(R) Xeon" device
    assert order_candidates([(pocl, "pocl")], "intel") == []


def test_a_runtime_that_cannot_build_falls_back_to_the_next() -> None:
    # PoCL 3.0 on Zen 5: every build fails; Intel's runtime is used instead
    def probe(device: Any, nt_store: bool) -> str | None:
        return ZEN5 if device == "pocl" else None

    choice = choose_device("auto", FOUND, probe)
    assert choice.candidate == INTEL and choice.nontemporal_stores
    tried = dict(choice.tried)
    assert tried[POCL] == ZEN5
    assert tried[GPU].startswith("not tried")


def test_a_device_without_streaming_stores_is_used_with_plain_stores() -> None:
    def probe(device: Any, nt_store: bool) -> str | None:
        return "build failed: no __builtin_nontemporal_store" if nt_store else None

    choice = choose_device("gpu", FOUND, probe)
    assert choice.candidate == GPU and not choice.nontemporal_stores


def test_no_working_device_names_each_one_and_what_to_install() -> None:
    with pytest.raises(InputError) as err:
        choose_device("auto", FOUND, lambda device, nt: ZEN5)
    msg = str(err.value)
    for cand in (POCL, INTEL, GPU):
        assert f"{cand.label}: {ZEN5}" in msg
    assert "pip install 'skinpipe[intel-cpu]'" in msg and "--device" in msg
    with pytest.raises(InputError, match="no OpenCL device found"):
        choose_device("auto", [], lambda device, nt: None)
    with pytest.raises(InputError, match="matches 'amd-gpu'"):
        choose_device("amd-gpu", FOUND, lambda device, nt: None)


def test_every_device_here_passes_the_probe_or_says_why() -> None:
    found = choice.candidates(all_runtimes=True)
    assert found, "pyopencl[pocl] brings at least PoCL"
    for cand, device in found:
        reason = choice.probe(device)
        assert reason is None or reason.count("\n") == 0, (cand.label, reason)


@pytest.mark.skipif(not _intel_installed(), reason="intel-opencl-rt is not installed")
def test_intel_runtime_is_registered_and_survives_pymeshlab() -> None:
    # pymeshlab through skinpipe (the newer TBB first): Intel's platform stays
    code = ("from skinpipe.native import import_pymeshlab; import_pymeshlab();"
            "from skinpipe.render.device import choice;"
            "print('|'.join(c.platform for c, _ in choice.candidates(all_runtimes=True)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    assert "Intel(R) OpenCL" in out and "Portable Computing Language" in out
    vendors = Path(os.environ["OCL_ICD_VENDORS"])
    icd = (vendors / "skinpipe-intel-cpu.icd").read_text().strip()
    assert Path(icd).is_absolute() and Path(icd).name == "libintelocl.so"


_LOADED = ("from skinpipe.render.device import choice, runtimes; c = choice.open_device().choice;"
           "maps = open('/proc/self/maps').read();"
           "print(c.candidate.runtime, 'libintelocl' in maps, runtimes.SETUP.notes)")


@pytest.mark.skipif(not _intel_installed() or not Path("/proc/self/maps").exists(),
                    reason="intel-opencl-rt is not installed, or no /proc")
def test_intel_runtime_is_loaded_only_where_it_may_be_used(tmp_path: Path) -> None:
    """Read from the process's own memory map: Intel's library is loaded by a first
    process on a CPU (no record yet), not by a later one once PoCL has passed the probe
    here, and again by one that asks for Intel or for every device."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("OCL_ICD_VENDORS", "SKINPIPE_OPENCL_DEVICE")}
    env["XDG_CACHE_HOME"] = str(tmp_path)  # no record of an earlier probe

    def run(code: str = _LOADED, **extra: str) -> str:
        return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              timeout=300, check=True, env={**env, **extra}).stdout

    first = run()
    assert first.startswith("pocl-cpu True") or first.startswith("intel-cpu True"), first
    second = run()
    if first.startswith("pocl-cpu"):
        assert second.startswith("pocl-cpu False"), second
        assert "PoCL passed skinpipe's probe on this CPU before" in second
    else:  # PoCL failed the probe here (a CPU newer than its LLVM): Intel's every time
        assert second.startswith("intel-cpu True"), second
    assert run(SKINPIPE_OPENCL_DEVICE="intel").startswith("intel-cpu True")
    if first.startswith("pocl-cpu"):
        # Intel's asked for only after a first query left it out: an error that says so,
        # and asked for again, the note once
        late = run("from skinpipe.render.device import choice, runtimes; choice.open_device()\n"
                   "for _ in range(2):\n"
                   "    try: choice.open_device('intel')\n"
                   "    except Exception as exc: print(type(exc).__name__, exc)\n"
                   "print(sum('first OpenCL query' in n for n in runtimes.SETUP.notes))")
        assert late.startswith("InputError") and "first OpenCL query" in late, late
        assert late.splitlines()[-1] == "1", late
    every = run("from skinpipe.render.device import choice, runtimes;"
                "print(sorted({c.runtime for c, _ in choice.candidates(all_runtimes=True)}))")
    assert "intel-cpu" in every and "pocl-cpu" in every, every


def test_the_pocl_record_is_kept_dropped_and_never_fails(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A pass keeps the record, a failure drops it, and a cache folder that cannot hold
    it (a file where the folder should be) neither raises nor claims a pass."""
    from skinpipe.render.device.runtimes import note_pocl_probe, pocl_passed_here

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    assert not pocl_passed_here()
    note_pocl_probe(True)
    assert pocl_passed_here()
    note_pocl_probe(False)
    assert not pocl_passed_here()
    (tmp_path / "file").write_text("not a folder")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "file"))
    note_pocl_probe(True)
    assert not pocl_passed_here()


@pytest.mark.skipif(not _intel_installed(), reason="intel-opencl-rt is not installed")
def test_pymeshlab_first_is_reported() -> None:
    code = "import pymeshlab, skinpipe.render.device.runtimes as r; print(r.SETUP.notes)"
    env = {k: v for k, v in os.environ.items() if k != "OCL_ICD_VENDORS"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True, env=env).stdout
    assert "pymeshlab was loaded first" in out


def _skinpipe(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "skinpipe", *args], capture_output=True,
                          text=True, timeout=300, env={**os.environ, **env})


def test_env_names_the_chosen_device_and_why_not_the_others() -> None:
    r = _skinpipe("env")
    assert r.returncode == 0, r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.startswith("#")]
    assert lines[0].startswith("# OpenCL device ('auto'): ")
    assert len(lines) - 1 >= len(choice.candidates()) - 1


def test_unknown_device_is_one_clear_error_without_traceback() -> None:
    r = _skinpipe("env", SKINPIPE_OPENCL_DEVICE="no-such-device")
    assert r.returncode == 2
    assert "Traceback" not in r.stderr
    err = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(err) == 1 and "no OpenCL device matches 'no-such-device'" in err[0]


def test_ledger_counts_builds_and_launches(cl_device: choice.Device) -> None:
    import pyopencl as cl

    before = programs.LEDGER.copy()
    # launched without a local size, the grid is padded: the kernel tests its bounds
    program = programs.build(cl_device, "__kernel void twice(__global float *a, const int n)"
                           "{ if (get_global_id(0) < n) a[get_global_id(0)] *= 2.0f; }")
    kernel = programs.Kernel(program, "twice", 1)
    ctx, queue = cl_device.context, cl_device.queue
    a = np.arange(8, dtype=np.float32)
    buf = cl.Buffer(ctx, cl.mem_flags.READ_WRITE | cl.mem_flags.COPY_HOST_PTR, hostbuf=a)
    kernel(queue, (8,), None, buf, np.int32(8))
    kernel(queue, (8,), None, buf, np.int32(8))
    out = np.empty_like(a)
    cl.enqueue_copy(queue, out, buf)
    np.testing.assert_array_equal(out, 4 * a)
    since = programs.LEDGER.since(before)
    assert since["programs_built"] == 1 and since["build_seconds"] >= 0
    assert since["kernel_launches"] == {"twice": 2}


def test_an_empty_output_reads_back_without_a_map(cl_device: choice.Device) -> None:
    # OpenCL refuses to map zero bytes (clEnqueueMapBuffer: INVALID_VALUE): an empty
    # output has nothing to read back, and its buffer (one placeholder element) stays
    empty = np.empty((0, 3), np.float32)
    memory.read_output(cl_device, memory.host_output(cl_device, empty), empty)
    assert empty.shape == (0, 3)


_HALF_TEST_KERNELS = r"""
__kernel void decode(__global const ushort *h, const int n, __global float *out)
{
    const int i = get_global_id(0);
    if (i < n) out[i] = half_bits_to_float(h[i]);
}
__kernel void encode(__global const float *f, const int n, __global ushort *out)
{
    const int i = get_global_id(0);
    if (i < n) out[i] = float_to_half_bits(f[i]);
}
"""


def _half_kernel(device: choice.Device, name: str) -> object:
    from skinpipe.render.device.programs import HALF_BITS, Kernel, build

    return Kernel(build(device, HALF_BITS + _HALF_TEST_KERNELS), name, 1)


def test_half_bits_decode_as_numpy_does_every_finite_half(cl_device: choice.Device) -> None:
    from skinpipe.render.device.memory import run_on_host_arrays

    bits = np.arange(1 << 16, dtype=np.uint16)
    bits = bits[np.isfinite(bits.view(np.float16))]
    out = np.empty(bits.size, np.float32)
    run_on_host_arrays(_half_kernel(cl_device, "decode"), cl_device, (bits.size,),
                       [bits, np.int32(bits.size)], [out])
    np.testing.assert_array_equal(out.view(np.uint32),
                                  bits.view(np.float16).astype(np.float32).view(np.uint32))


def test_half_bits_encode_rounds_as_numpy_does(cl_device: choice.Device) -> None:
    # every half's value, the midpoints between neighbours (ties: to even) and one float
    # ulp either side of them, and random floats across half's normal and subnormal range
    from skinpipe.render.device.memory import run_on_host_arrays

    halves = np.arange(0x7bff + 1, dtype=np.uint16).view(np.float16).astype(np.float32)
    mid = (halves[:-1] + halves[1:]) / np.float32(2)
    rng = np.random.default_rng(4)
    f = np.concatenate([halves, mid, np.nextafter(mid, np.float32(0)),
                        np.nextafter(mid, np.float32(np.inf)),
                        rng.random(200_000, np.float32) * np.float32(2),
                        rng.random(200_000, np.float32) * np.float32(2e-4),
                        np.float32(10.0) ** rng.uniform(-9, 4.8, 200_000).astype(np.float32)])
    f = np.concatenate([f, -f])
    out = np.empty(f.size, np.uint16)
    run_on_host_arrays(_half_kernel(cl_device, "encode"), cl_device, (f.size,),
                       [f, np.int32(f.size)], [out])
    np.testing.assert_array_equal(out, f.astype(np.float16).view(np.uint16))
