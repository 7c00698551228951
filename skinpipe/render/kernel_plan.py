"""The device kernels a render will need, in the order it needs them: what a
:class:`~.device.programs.Prewarm` builds (and on PoCL compiles) while the host works
on the frame's first tasks."""

from __future__ import annotations

from collections.abc import Callable, Collection, Sequence
from functools import partial
from typing import Any

from .device.choice import Device
from .device.memory import streams
from .diffusion.blur_switch import TUNE_STREAM, tuning_kernels
from .diffusion.chart_tiles import seam_read_kernel
from .diffusion.direct_blur import texel_kernels
from .diffusion.layout import pyramid_kernels
from .diffusion.margins import margin_kernels
from .diffusion.push_pull import push_pull_kernels
from .diffusion.recursive_blur import pass_kernels
from .light.irradiance import irradiance_kernels
from .options import RenderOptions
from .scene import Light
from .surface.texture_maps import texture_kernels


def kernel_plan(device: Device, opts: RenderOptions, lights: Sequence[Light],
                periods: Collection[int], regions: Collection[int]
                ) -> list[Callable[[], Any]]:
    """The kernel builders a render with ``opts`` on ``device`` calls, each a step
    returning the kernels it made: the texture maps', the shadow rays' and their filter's
    for ``lights`` at each interleaving period of ``periods``, the push-pull's, and for
    the recursive diffusion the seam layout's, the accumulation's for each count of
    region weights a texel in ``regions`` (0: one region), the blurs' and the blur
    switch's."""
    domes = [lt.path for lt in lights if lt.kind == "dome" and lt.texture]
    steps: list[Callable[[], Any]] = [
        partial(texture_kernels, device),
        *(partial(irradiance_kernels, device, lights, opts.light_samples,
                  opts.shadow_sampling != "full", domes,
                  filtered=opts.shadow_sampling == "interleaved",
                  sequence=opts.light_sequence,
                  refined=opts.shadow_sampling == "adaptive", period=p)
          for p in sorted(periods)),
        partial(push_pull_kernels, device)]
    if opts.scattering and opts.blur == "recursive":
        # the seam layout's, made beside the irradiance
        steps.insert(1 + len(periods), partial(margin_kernels, device))
        steps += [partial(pyramid_kernels, device, r) for r in sorted(regions)]
        steps.append(partial(seam_read_kernel, device))
        stream = streams(opts.texture_size ** 2 * 16)
        # the finest level, the coarser ones (smaller: plain stores), the switch's
        steps += [partial(pass_kernels, device, s)
                  for s in dict.fromkeys((stream, False, TUNE_STREAM))]
        steps += [partial(tuning_kernels, device), partial(texel_kernels, device, stream)]
    return steps
