"""``skinpipe render``: texture-space diffusion renders of a USD scene."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from ..errors import EXIT_OK
from .common import (
    HelpFormatter,
    TaskBar,
    _frames,
    add_force_option,
    add_render_options,
    ocio_source,
    render_options,
)


def _print_render(doc: dict[str, Any]) -> None:
    for frame in doc["frames"]:
        tasks = ", ".join(f"{k} {v:.2f} s" for k, v in frame["tasks"].items())
        label = "" if frame["frame"] is None else f"frame {frame['frame']}: "
        print(f"{label}{frame['outputs']['exr']} ({frame['seconds']:.1f} s: {tasks}"
              f"{'; cached ' + ', '.join(frame['cached']) if frame['cached'] else ''})")
        diff = frame["measures"].get("diffusion", {})
        if diff:
            print(f"  diffusion: {len(diff['variances_mm2'])} variances, "
                  f"{diff['blur_passes']} blur passes, energy ratio "
                  f"{diff['energy_ratio']:.4f}, grid error (eq. 2c) max "
                  f"{max(diff['grid_error_eq2c'].values()):.2e}, light within a radius "
                  f"max {max(diff['grid_edge_error'].values()):.2e}")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
        help="render a USD scene with texture-space subsurface diffusion",
        description=(
            "Render SCENE (an asset with skin profiles, plus a camera and UsdLux lights; "
            "'skinpipe shot' makes such a layer): xatlas UVs where the mesh has none "
            "(written back into the asset's geo layer), texture maps, irradiance with "
            "Embree shadow rays, OpenCL diffusion with the fitted profiles, "
            "Torrance-Sparrow specular. Writes OUT/<name>.exr (ACEScg, one layer per AOV), "
            "OUT/<name>.png (display view through OCIO) and OUT/render.json (each task's "
            "seconds, what was cached or skipped, error measures). With --frames, one pair "
            "per frame; texture-space work is reused while only the camera moves."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("scene", type=Path, help="USD scene or asset to render")
    add_render_options(p)
    p.add_argument("--frames", type=_frames, default=None, metavar="A:B",
                   help="render time codes A..B (e.g. a turntable from 'skinpipe shot')")
    p.add_argument("--name", default=None, help="image name (default: the scene's stem)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    add_force_option(p)
    p.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from ..fileio import check_path_name, staged_output_directory
    from ..render.options import TASK_SHARES
    from ..render.outputs import render_files
    from ..usd.io import usd_inputs

    name = check_path_name(args.name or args.scene.stem, "image name (--name)")
    frames = [name] if args.frames is None else \
        [f"{name}.{t:04d}" for t in range(args.frames[0], args.frames[1] + 1)]
    expect = [f"{f}{ext}" for f in frames for ext in (".exr", ".png", "_uv.exr")] + \
        ["render.json"]
    reads = usd_inputs(args.scene)
    options = render_options(args)
    ocio = ocio_source(args)
    with TaskBar(TASK_SHARES, len(frames)) as bar, \
            staged_output_directory(args.output, "render", reads, args.force, expect) as out:
        doc = render_files(args.scene, out.path, options, args.frames, ocio, name,
                           progress=bar)
    doc = out.final(doc)
    _print_render(doc)
    print(f"wrote {args.output / 'render.json'} ({doc['total_seconds']:.1f} s)")
    return EXIT_OK
