"""Compiling ahead of use: padded launches, the prewarm thread, and the render's plan of
kernels (skinpipe/render/device/programs.py, light sampling plans)."""

from __future__ import annotations

import re
from functools import partial

import numpy as np
import pytest

import skinpipe.render.diffusion.chart_tiles as chart_tiles_module
import skinpipe.render.diffusion.gather as gather_module
import skinpipe.render.diffusion.layout as layout_module
import skinpipe.render.diffusion.margins as margins_module
from skinpipe.render.device import programs
from skinpipe.render.device.choice import Device
from skinpipe.render.device.programs import fixed_local_size
from skinpipe.render.diffusion import direct_blur, push_pull, recursive_blur
from skinpipe.render.light import irradiance, samples
from skinpipe.render.light.samples import LightSampler, sample_plan
from skinpipe.render.scene import Light
from skinpipe.render.surface import texture_maps

KERNEL_SOURCES = {
    "chart_tiles": margins_module._MARGIN_KERNEL + chart_tiles_module._SEAM_READ_KERNEL,
    "diffusion": gather_module._KERNEL + layout_module._PYRAMID_KERNEL,
    "direct_blur": direct_blur._KERNEL,
    "lighting": samples._SAMPLE_KERNEL + irradiance._INTERLEAVE_KERNEL,
    "push_pull": push_pull._KERNEL,
    "recursive_blur": recursive_blur._KERNEL,
    "texture_maps": texture_maps._KERNEL,
}


def test_fixed_local_size_pads_the_grid_and_fits_the_kernel() -> None:
    assert fixed_local_size((1000,), 1024) == ((1024,), (256,))
    assert fixed_local_size((1000, 3), 1024) == ((1024, 8), (32, 8))
    # a kernel that allows 64 work items: the first axis halves first
    assert fixed_local_size((1000, 3), 64) == ((1000, 8), (8, 8))
    assert fixed_local_size((5, 5), 1) == ((5, 5), (1, 1))


@pytest.mark.parametrize("module", sorted(KERNEL_SOURCES))
def test_every_kernel_returns_at_its_bounds_test(module: str) -> None:
    """A padded grid (and Kernel.warm's launch with every size 0) runs work items past
    the data: each kernel must return before it touches memory."""
    source = KERNEL_SOURCES[module]
    kernels = list(re.finditer(r"__kernel\s+void\s+(\w+)\s*\(", source))
    assert kernels, module
    for k in kernels:
        body = source[source.index("{", k.end()):]
        head = body[:body.index("return;") + 7] if "return;" in body else ""
        assert re.search(r"if \(!?\(?[^;{}]*>=[^;{}]*\)\s*return;", head), \
            f"{module}: kernel {k.group(1)} has no bounds test before its first statement"
        # the test comes before any store: nothing is assigned through a pointer first
        assert "] =" not in head and "STORE(" not in head, k.group(1)


def test_prewarm_builds_ahead_and_the_render_finds_its_programs(cl_device: Device) -> None:
    def fails() -> None:
        raise RuntimeError("a step that fails is skipped")

    push_pull.push_pull_kernels.cache_clear()
    before = programs.LEDGER.copy()
    pre = programs.start_prewarm(cl_device, [fails, partial(push_pull.push_pull_kernels,
                                                            cl_device)])
    programs.wait_for_prewarm()
    since = programs.LEDGER.since(before)
    assert since["kernels_prewarmed"] == 3 and pre.seconds > 0
    # the render's own call finds the program built (no second build)
    built = since["programs_built"]
    pull, _, _ = push_pull.push_pull_kernels(cl_device)
    assert programs.LEDGER.since(before)["programs_built"] == built
    # and the prewarmed kernel computes (the fill of an empty texel)
    v = np.zeros((6, 5, 3), np.float32)
    c = np.zeros((6, 5), np.float32)
    v[2, 3], c[2, 3] = (1.0, 2.0, 3.0), 1.0
    out = push_pull.push_pull(v, c, device=cl_device)
    np.testing.assert_allclose(out[0, 0], (1.0, 2.0, 3.0), rtol=1e-5)
    assert pull.name == "pull"


@pytest.mark.parametrize("kind", ["sphere", "distant", "dome"])
@pytest.mark.parametrize("samples", [1, 4, 9, 16])
@pytest.mark.parametrize("interleaved", [False, True])
def test_sample_plan_is_what_the_sampler_traces(kind: str, samples: int,
                                                interleaved: bool) -> None:
    matrix = np.eye(4)
    matrix[3, :3] = (0.0, 0.0, 50.0)
    light = Light("/L", kind, np.ones(3), matrix, radius=4.0,
                  angle_deg=0.0 if kind == "distant" else 0.53)
    pts = np.zeros((4, 3), np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (4, 1))
    classes = np.arange(4) if interleaved else None
    sampler = LightSampler(light, pts, nrm, samples, np.random.default_rng(0),
                           interleave=classes)
    count, inter = sample_plan(light, samples, interleaved)
    assert (count, inter) == (sampler.count, sampler.sets is not None)


def test_a_step_that_fails_costs_only_time(cl_device: Device) -> None:
    """A step that raises is skipped (the render meets it again where its error is
    reported); the steps after it still run."""
    def missing() -> None:
        raise ImportError("no such kernels")

    push_pull.push_pull_kernels.cache_clear()
    before = programs.LEDGER.copy()
    programs.start_prewarm(cl_device, [missing, partial(push_pull.push_pull_kernels,
                                                        cl_device)])
    programs.wait_for_prewarm()
    assert programs.LEDGER.since(before)["kernels_prewarmed"] == 3
