"""Shared fixtures."""

from __future__ import annotations

import contextlib
import io
import os
from collections.abc import Iterator
from pathlib import Path

import pytest

from skinpipe.profile.types import MeasuredProfile
from skinpipe.render.device import choice
from skinpipe.render.diffusion.blur_switch import SWITCH_ENV
from skinpipe.render.diffusion.direct_blur import FIR_MAX_RADIUS, FIR_MAX_RADIUS_PER_TEXEL
from skinpipe.render.options import DEVICE_ENV

from .reference_profiles import deon_profile

# Which blur runs is measured per device (render.diffusion.blur_switch); tests that count blur
# passes pin it to the values measured on PoCL. tests/render/diffusion/test_blur_switch.py measures.
os.environ[SWITCH_ENV] = f"{FIR_MAX_RADIUS},{FIR_MAX_RADIUS_PER_TEXEL}"


def _working_devices() -> list[choice.Candidate]:
    """Every OpenCL device here that passes skinpipe's probe (one runtime each once)."""
    out: list[choice.Candidate] = []
    for cand, device in choice.candidates(all_runtimes=True):
        if choice.probe(device) is None and cand.runtime not in [c.runtime for c in out]:
            out.append(cand)
    return out


OPENCL_DEVICES = _working_devices()


@pytest.fixture(scope="session", params=OPENCL_DEVICES, ids=lambda c: c.runtime)
def cl_device(request: pytest.FixtureRequest) -> Iterator[choice.Device]:
    """Runs a test on each OpenCL device that passes the probe (pocl-cpu, intel-cpu, a
    GPU): a runtime-specific failure shows by name. The device is the environment's
    meanwhile (``$SKINPIPE_OPENCL_DEVICE``: what a step given no device runs on, as a
    user's would); session scope, so pytest groups the tests by device and each
    device's programs are built once."""
    before = os.environ.get(DEVICE_ENV)
    os.environ[DEVICE_ENV] = request.param.runtime
    yield choice.open_device()
    if before is None:
        os.environ.pop(DEVICE_ENV, None)
    else:
        os.environ[DEVICE_ENV] = before


@pytest.fixture
def deon() -> MeasuredProfile:
    return deon_profile()


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str, str]:
    """`skinpipe demo` at its defaults (the README's first command), run once per test
    session: its output folder, stdout and stderr. Tests read what it wrote; none
    writes into it."""
    from skinpipe.cli import main

    out = tmp_path_factory.mktemp("demo") / "demo_out"
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["demo", "-o", str(out)])
    assert code == 0, stderr.getvalue()[-3000:]
    return out, stdout.getvalue(), stderr.getvalue()
