"""``skinpipe paint-albedo``: a procedural skin albedo for an asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK
from .common import _eprint


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "paint-albedo",
        help="paint a plausible skin albedo texture on an asset that has none",
        description=(
            "For an asset without colour (like the sample face scan): unwrap the skin mesh "
            "if it has no usable UVs (written back into its geo layer), paint a tone per "
            "region with freckles and moles (sizes in mm on the surface), write "
            "albedo.exr (ACEScg) beside the asset and bind it to the material's "
            "diffuseColor. Changes the asset's geo and look layers in place (atomically)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("asset", type=Path)
    p.add_argument("--size", type=int, default=2048, help="texture size in texels")
    p.add_argument("--seed", type=int, default=7, help="freckle and mole placement")
    p.set_defaults(handler=cmd_paint_albedo)


def cmd_paint_albedo(args: argparse.Namespace) -> int:
    from ..render.albedo import bake_sample_albedo

    print(f"wrote {bake_sample_albedo(args.asset, args.size, args.seed, _eprint)}")
    return EXIT_OK
