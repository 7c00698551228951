"""A render's files: the EXR of its AOVs (ACEScg, chromaticities in the header), the
display PNG through the OCIO config's display and view, texture-space images on request,
and ``render.json``; and ``render_files``, which renders a scene file's frames into a
folder."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import PyOpenColorIO as OCIO
from numpy.typing import NDArray
from pxr import Tf

from ..errors import SkinpipeError
from ..fileio import atomic_write_json
from ..imageio import (
    check_colorspace,
    ocio_config,
    write_exr,
    write_ldr,
)
from ..usd.io import open_stage_guarded
from .bands import BAND_THREADS, host_threads, in_bands
from .budget import check_render_fits
from .device.choice import Device
from .device.programs import LEDGER, KernelLedger
from .diffusion.blur_switch import direct_limits
from .frame import SkinTextures
from .options import RenderOptions
from .renderer import Renderer

HALF_MAX = 65504.0
"""The largest finite half float."""


def texture_space_images(tex: SkinTextures, which: tuple[str, ...]
                         ) -> dict[str, NDArray[np.float32]]:
    """The texture-space maps ``which`` (:data:`~.options.TEXTURE_OUTPUTS`) of one skin
    mesh, rows flipped so that row 0 is v = 1 (as a texture image), plus coverage."""
    maps = tex.maps
    covered = maps.triangle >= 0
    out: dict[str, NDArray[np.float32]] = {}
    if "irradiance" in which and tex.irradiance is not None:
        out["irradiance"] = tex.irradiance
    if "radiosity" in which and tex.radiosity is not None:
        out["radiosity"] = (tex.radiosity * np.float32(math.pi)) * covered[..., None]
    if "stretch" in which:
        out["stretch"] = np.stack([maps.mm_per_texel_u, maps.mm_per_texel_v], axis=-1)
    if "region" in which:
        region = np.full(covered.shape, -1.0, np.float32)
        if maps.region_weights is not None:
            region[covered] = np.argmax(maps.region_weights[covered], axis=-1)
        out["region"] = region[..., None]
    out["coverage"] = maps.coverage[..., None]
    return {k: np.ascontiguousarray(v[::-1], np.float32) for k, v in out.items()}


_TEXTURE_CHANNELS = {"irradiance": ("R", "G", "B"), "radiosity": ("R", "G", "B"),
                     "stretch": ("u_mm", "v_mm"), "region": ("id",), "coverage": ("A",)}


def write_texture_outputs(out_dir: Path, name: str, renderer: Renderer, working: str
                          ) -> list[str]:
    """``<name>_uv.exr`` (``<name>_uv_<mesh>.exr`` for each of several skin meshes) with
    the options' texture-space maps; their paths."""
    which = renderer.options.texture_outputs
    paths = []
    for tex in renderer.textures if which else []:
        images = texture_space_images(tex, which)
        suffix = "" if len(renderer.textures) == 1 else \
            "_" + Tf.MakeValidIdentifier(tex.mesh.path.strip("/").replace("/", "_"))
        names = [f"{k}.{c}" for k in images for c in _TEXTURE_CHANNELS[k]]
        exr = write_exr(out_dir / f"{name}_uv{suffix}.exr",
                        np.concatenate(list(images.values()), axis=2), working,
                        channel_names=tuple(names))
        paths.append(str(exr))
    return paths


# ------------------------------------------------------------------------ outputs


def display_image(beauty: NDArray[Any], working: str, config_source: str
                  ) -> tuple[NDArray[np.float32], dict[str, str]]:
    """Display-referred pixels through the config's default display and view, of the
    colour itself (a premultiplied beauty with alpha is divided by its alpha first: the
    view transform is not linear, and applied to colour times coverage it brightened the
    demo face's 2526 silhouette pixels by 0.12 of the display's range on average, 0.46
    at most, once the PNG's straight alpha was taken off)."""
    config = ocio_config(config_source)
    src = check_colorspace(working, config_source)
    display = config.getDefaultDisplay()
    view = config.getDefaultView(display)
    transform = OCIO.DisplayViewTransform(src=src, display=display, view=view)
    proc = config.getProcessor(transform).getDefaultCPUProcessor()
    rgb = np.nan_to_num(beauty[..., :3].astype(np.float32), copy=False, nan=0.0, posinf=1e4)
    if beauty.shape[-1] == 4:
        alpha = beauty[..., 3:4]
        np.divide(rgb, alpha, out=rgb, where=alpha > 0)
    # in row bands on the cores: OCIO lets go of the GIL, and the default view's ACES 2.0
    # output transform took 0.45 s for a 768 x 768 image on one core (0.23 s on two); a
    # pixel's value does not depend on the band
    pixels = rgb.reshape(-1, 3)
    in_bands(lambda rows: proc.applyRGB(pixels[rows]), pixels.shape[0],
             -(-pixels.shape[0] // min(host_threads(), BAND_THREADS)))
    return np.clip(rgb, 0, 1), {"display": display, "view": view, "config": config_source}


def display_colorspace(config_source: str, display: str, view: str) -> str:
    """The colour space a display/view pair's output is encoded in. OCIO 2.2+ configs
    share views across displays and answer ``<USE_DISPLAY_NAME>``: the colour space
    named as the display itself (OCIO's rule for shared views)."""
    space = ocio_config(config_source).getDisplayViewColorSpaceName(display, view)
    return display if space == OCIO.OCIO_VIEW_USE_DISPLAY_NAME else space


def write_outputs(out_dir: Path, name: str, images: dict[str, NDArray[np.float32]],
                  working: str, config_source: str, half: bool = False) -> dict[str, Any]:
    """OUT/<name>.exr (one layer per AOV, colour space in the header; half float with
    ``half``, where no value exceeds half's range) and OUT/<name>.png."""
    channels, names = [], []
    for aov, img in images.items():
        chans = {4: ("R", "G", "B", "A"), 3: ("R", "G", "B"), 1: ("id",)}[img.shape[2]]
        channels.append(img)
        names += [c if aov == "beauty" else f"{aov}.{c}" for c in chans]
    stack = np.concatenate(channels, axis=2)
    if not np.all(np.isfinite(stack)):
        raise SkinpipeError(f"{name}: the render produced non-finite pixels")
    if half and np.abs(stack).max() > HALF_MAX:
        raise SkinpipeError(f"{name}: a pixel exceeds half float's range ({HALF_MAX}); "
                            "write float EXRs (leave out --half-float)")

    def preview() -> dict[str, Any]:
        disp, info = display_image(images["beauty"], working, config_source)
        alpha = images["beauty"][..., 3:4]
        # tagged with the display's colour space, so the PNG carries its sRGB chunk
        space = display_colorspace(config_source, info["display"], info["view"])
        # straight alpha, as PNG stores it: OpenImageIO is told so, or it divides again
        png = write_ldr(out_dir / f"{name}.png", np.concatenate([disp, alpha], axis=2), 8,
                        {"oiio:ColorSpace": space, "oiio:UnassociatedAlpha": 1,
                         "skinpipe:displayView": f"{info['display']} / {info['view']}"})
        return {"png": str(png), **info}

    # the PNG's display transform and writing on a thread beside the EXR's (OpenImageIO
    # and OCIO let Python's lock go): the demo scene's 1024 x 1024 frame 0.43-0.69 ->
    # 0.36-0.38 s
    with ThreadPoolExecutor(1, thread_name_prefix="skinpipe-png") as side:
        png = side.submit(preview) if "beauty" in images else None
        exr = write_exr(out_dir / f"{name}.exr", stack, working, channel_names=tuple(names),
                        half=half)
        result: dict[str, Any] = {"exr": str(exr), "colorspace": working}
        if png is not None:
            result.update(png.result())
    return result


def render_files(scene_path: Path, out_dir: Path, options: RenderOptions,
                 frames: tuple[int, int] | None = None, ocio: str = "ocio://default",
                 name: str | None = None, progress: Callable[[str], None] | None = None,
                 renderer: Renderer | None = None) -> dict[str, Any]:
    """Render ``scene_path`` into ``out_dir`` (one EXR + PNG per frame) and write
    ``render.json``: per frame, each task's seconds, what was cached or skipped, and the
    error measures. A ``renderer`` passed in is used (and left open) so that its caches
    serve later renders of the same stage."""
    start = time.perf_counter()
    scene_path = Path(scene_path)
    check_colorspace("lin_ap1_scene", ocio)
    check_render_fits(options.texture_size, options.resolution)
    name = name or scene_path.stem
    own = renderer is None
    if renderer is None:
        renderer = Renderer(open_stage_guarded(scene_path), options, progress)
    renderer.options = options
    ledger = LEDGER.copy()
    out_dir.mkdir(parents=True, exist_ok=True)
    doc: dict[str, Any] = {"scene": str(scene_path), "options": _options_json(options),
                           "ocio": ocio, "frames": []}
    try:
        times = [None] if frames is None else list(range(frames[0], frames[1] + 1))
        for t in times:
            t0 = time.perf_counter()
            if progress and t is not None:
                progress(f"frame {t}")
            renderer.last_frame = own and t == times[-1]
            images, log = renderer.render(t)
            frame_name = name if t is None else f"{name}.{t:04d}"
            uv_outputs = write_texture_outputs(out_dir, frame_name, renderer,
                                               renderer.delegate.working_colorspace)
            if own and t == times[-1]:
                renderer.clear_cache()  # no frame follows: its textures go before the writes
            working = renderer.delegate.working_colorspace
            outputs = write_outputs(out_dir, frame_name, images, working, ocio,
                                    options.half_float)
            if uv_outputs:
                outputs["texture_space"] = uv_outputs
            doc["frames"].append({"frame": t, "seconds": time.perf_counter() - t0,
                                  "tasks": log.seconds, "cached": log.cached,
                                  "skipped": log.skipped, "measures": log.measures,
                                  "outputs": outputs})
    finally:
        if own:
            renderer.close()
    doc["total_seconds"] = time.perf_counter() - start
    doc["opencl"] = opencl_summary(renderer.device, ledger)
    atomic_write_json(out_dir / "render.json", doc)
    return doc


def opencl_summary(device: Device, before: KernelLedger) -> dict[str, Any]:
    """The device, why the others were not used, the programs built and their seconds,
    the kernels launched since ``before``, and the direct/recursive blur switch used."""
    doc = {**device.choice.summary(), **LEDGER.since(before)}
    used = direct_limits(device)
    if used is not None:  # only if a blur asked for it
        doc["blur_switch"] = asdict(used)
    return doc


def _options_json(options: RenderOptions) -> dict[str, Any]:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(options).items()}
