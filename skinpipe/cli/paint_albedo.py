"""``skinpipe paint-albedo``: a procedural skin albedo for an asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "paint-albedo",
        help="paint a plausible skin albedo texture on an asset that has none",
        description=(
            "For an asset without colour (like the sample face scan): unwrap the skin mesh "
            "if it has no usable UVs (written back into its geo layer), paint a tone per "
            "region with freckles and moles (sizes in mm on the surface), write "
            "albedo.exr (ACEScg) beside the asset and bind it to every material's "
            "diffuseColor and OpenPBR base colour; where the profiles carry their media, "
            "also subsurface_color.exr and subsurface_radius_scale.exr, the regions' "
            "OpenPBR subsurface blended by their soft weights (the skinLook variant "
            "'blended' shows them). Changes the asset's geo and look layers in place "
            "(atomically)."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("asset", type=Path)
    p.add_argument("--size", type=int, default=2048, help="texture size in texels")
    p.add_argument("--seed", type=int, default=7, help="freckle and mole placement")
    add_force_option(p)
    p.set_defaults(handler=cmd_paint_albedo)


def cmd_paint_albedo(args: argparse.Namespace) -> int:
    from ..fileio import check_output_file, record_outputs
    from ..workflow.albedo import (
        ALBEDO_NAME,
        SUBSURFACE_COLOUR_NAME,
        SUBSURFACE_SCALE_NAME,
        bake_sample_albedo,
    )

    if not 16 <= args.size <= 16384:
        raise InputError(f"--size must be 16-16384 texels, got {args.size}")
    names = (ALBEDO_NAME, SUBSURFACE_COLOUR_NAME, SUBSURFACE_SCALE_NAME)
    texture, *_ = [check_output_file(args.asset.absolute().parent / name, (), args.force)
                   for name in names]
    print(f"wrote {bake_sample_albedo(args.asset, args.size, args.seed, _eprint)}")
    record_outputs(texture.parent, [n for n in names if (texture.parent / n).exists()],
                   "paint-albedo")
    return EXIT_OK
