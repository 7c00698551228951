"""``skinpipe inspect``: profile terms, errors and plots of an asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect",
        help="print an asset's fitted profiles and plot measured vs fitted",
        description=(
            "Print each SkinDiffusionProfile's terms per channel, eq. 2c errors and solver "
            "facts; --plot draws measured samples and fitted curves per channel with "
            "relative residuals (one PNG per profile when several are shown)."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("asset", type=Path, metavar="ASSET.usd")
    p.add_argument("--prim", default=None, help="a profile prim, or a mesh: its profiles")
    p.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                   help="plot file; with several profiles OUT_<region>.png each")
    p.add_argument("--log-radius", action="store_true", help="logarithmic radius axis")
    add_force_option(p)
    p.set_defaults(handler=cmd_inspect)


def cmd_inspect(args: argparse.Namespace) -> int:
    from pxr import Tf

    from ..fileio import check_output_file, record_outputs
    from ..usd.inspection import (
        describe_medium,
        describe_profile,
        plot_profile,
        profiles_on_stage,
    )
    from ..usd.io import open_stage_guarded, usd_inputs
    from ..usd.schema import plugin_path_note

    reads = usd_inputs(args.asset)
    stage = open_stage_guarded(args.asset)
    note = plugin_path_note()
    if note:
        _eprint(note)
    found = profiles_on_stage(stage, args.prim)
    if not found:
        raise InputError(f"no SkinDiffusionProfile {'at ' + args.prim if args.prim else ''}"
                         .strip(), args.asset)
    plots = {path: args.plot if len(found) == 1 else args.plot.with_name(
        f"{args.plot.stem}_{Tf.MakeValidIdentifier(fit.name)}{args.plot.suffix}")
        for path, (fit, _) in found.items()} if args.plot is not None else {}
    for target in plots.values():
        check_output_file(target, reads, args.force)
    for path, (fit, measured) in found.items():
        print(describe_profile(path, fit, measured))
        medium = describe_medium(stage.GetPrimAtPath(path))
        if medium:
            print(medium)
        if path in plots:
            plot_profile(fit, measured, plots[path], log_radius=args.log_radius)
            record_outputs(plots[path].parent, [plots[path].name], "inspect")
            print(f"  plot: {plots[path]}")
    return EXIT_OK
