"""``skinpipe inspect``: profile terms, errors and plots of an asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import _eprint


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect",
        help="print an asset's fitted profiles and plot measured vs fitted",
        description=(
            "Print each SkinDiffusionProfile's terms per channel, eq. 2c errors and solver "
            "facts; --plot draws measured samples and fitted curves per channel with "
            "relative residuals (one PNG per profile when several are shown)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("asset", type=Path, metavar="ASSET.usd")
    p.add_argument("--prim", default=None, help="a profile prim, or a mesh: its profiles")
    p.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                   help="plot file; with several profiles OUT_<region>.png each")
    p.add_argument("--log-radius", action="store_true", help="logarithmic radius axis")
    p.set_defaults(handler=cmd_inspect)


def cmd_inspect(args: argparse.Namespace) -> int:
    from ..usd.inspection import describe_profile, plot_profile, profiles_on_stage
    from ..usd.io import open_stage_guarded
    from ..usd.schema import plugin_path_note

    stage = open_stage_guarded(args.asset)
    note = plugin_path_note()
    if note:
        _eprint(note)
    found = profiles_on_stage(stage, args.prim)
    if not found:
        raise InputError(f"no SkinDiffusionProfile {'at ' + args.prim if args.prim else ''}"
                         .strip(), args.asset)
    for path, (fit, measured) in found.items():
        print(describe_profile(path, fit, measured))
        if args.plot is not None:
            target = args.plot if len(found) == 1 else \
                args.plot.with_name(f"{args.plot.stem}_{fit.name}{args.plot.suffix}")
            plot_profile(fit, measured, target, log_radius=args.log_radius)
            print(f"  plot: {target}")
    return EXIT_OK
