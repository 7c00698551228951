"""``skinpipe ingest``: bracketed captures to HDR images and radial profiles."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ingest",
        help="merge bracketed captures to HDR and extract radial profiles (CAPTURES -> CSVs)",
        description=(
            "Read CAPTURES/capture.json (see docs/capture-format.md), merge each region's "
            "brackets into a scene-linear ACEScg HDR image, find the entry point to sub-pixel "
            "accuracy and extract the radial profile per channel in mm. Writes "
            "OUT_DIR/<region>.csv (radius_mm,R,G,B,std_R,std_G,std_B; integrating to 1 over "
            "the plane, the tail beyond the image extrapolated, unless --absolute), "
            "OUT_DIR/<region>.exr and ingest.json. "
            "Nothing is written unless every region succeeds."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("captures", type=Path, metavar="CAPTURES", help="capture-set directory")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.add_argument("--ring-width-px", type=float, default=1.0,
                   help="width of each ring, in camera pixels")
    p.add_argument("--max-radius-mm", type=float, default=None,
                   help="largest radius to extract (default: the largest ring inside the image)")
    p.add_argument("--mode", choices=["rings", "cross_section"], default="rings",
                   help="median over each ring, or the paper's single cross-section")
    p.add_argument("--absolute", action="store_true",
                   help="keep radiance units (per second of exposure) instead of normalising")
    p.add_argument("--merge", choices=["optimal", "hat"], default="optimal",
                   help="noise-optimal merge of linear captures (Granados et al. 2010), or "
                        "Debevec & Malik's hat weights (non-linear captures always use them)")
    p.add_argument("--no-core-model", dest="core_model", action="store_false",
                   help="ring medians from the entry point out, without modelling the core "
                        "below the pixel's size")
    p.add_argument("--no-tail", dest="extrapolate_tail", action="store_false",
                   help="normalise over the measured disk, without the tail beyond the image")
    p.add_argument("--regions", type=lambda t: [x for x in t.split(",") if x], default=None,
                   metavar="A,B", help="only these regions")
    add_force_option(p)
    p.set_defaults(handler=cmd_ingest)


def cmd_ingest(args: argparse.Namespace) -> int:
    from ..capture.ingest import IngestOptions, ingest_capture_set, read_capture_set
    from ..fileio import staged_output_directory

    if not args.ring_width_px > 0:
        raise InputError(f"--ring-width-px must be > 0, got {args.ring_width_px}")
    options = IngestOptions(ring_width_px=args.ring_width_px, max_radius_mm=args.max_radius_mm,
                            mode=args.mode, absolute=args.absolute, merge=args.merge,
                            core_model=args.core_model, extrapolate_tail=args.extrapolate_tail)
    captures = read_capture_set(args.captures)
    names = args.regions or list(captures.regions)
    expect = [f"{n}{ext}" for n in names for ext in (".csv", ".exr")] + ["ingest.json"]
    with staged_output_directory(args.output, "ingest", captures.files, args.force,
                                 expect) as out:
        report = ingest_capture_set(args.captures, out.path, options, progress=_eprint,
                                    regions=args.regions)
    report = out.final(report)
    for name, entry in report["regions"].items():
        print(f"{name}: {entry['samples']} samples to {entry['max_radius_mm']:.2f} mm "
              f"-> {entry['csv']}")
    return EXIT_OK
