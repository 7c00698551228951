"""``skinpipe shot``: a shot layer (camera, lights) over an asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK
from .common import HelpFormatter, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "shot",
        help="write a shot layer (camera, key and fill light) over an asset",
        description=(
            "Write OUT (.usda) that sublayers ASSET and adds /Shot/Camera framing the "
            "asset from the front (+Z, Y up), a key SphereLight (soft shadows) and a dim "
            "DomeLight fill. The asset is only read."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("asset", type=Path)
    p.add_argument("--turntable", type=int, default=0, metavar="N",
                   help="animate the camera once around the asset over frames 1..N")
    p.add_argument("--key-intensity", type=float, default=3.0,
                   help="irradiance the key light gives a surface facing it")
    p.add_argument("--fill-intensity", type=float, default=0.15, help="dome radiance")
    p.add_argument("-o", "--output", type=Path, required=True, help="shot layer to write")
    add_force_option(p)
    p.set_defaults(handler=cmd_shot)


def cmd_shot(args: argparse.Namespace) -> int:
    from ..fileio import check_output_file, record_outputs
    from ..usd.io import usd_inputs
    from ..usd.shot import ShotOptions, author_shot

    options = ShotOptions(key_intensity=args.key_intensity,
                          fill_intensity=args.fill_intensity, turntable_frames=args.turntable)
    check_output_file(args.output, usd_inputs(args.asset), args.force)
    out = author_shot(args.asset, args.output, options)
    record_outputs(args.output.parent, [args.output.name], "shot")
    print(f"wrote {out}")
    return EXIT_OK
