"""``skinpipe simulate``: capture sets with known truth from the simulator."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a physically simulated capture set with known true profiles",
        description=(
            "Render single-pixel scattering captures of the six face regions of a sample "
            "subject (forehead from Park & Oh 2009; the others from Jensen et al. 2001's "
            "measured skin coefficients, varied per region): a Gaussian projector "
            "footprint, pixel integration, hard-edged hair strands, photon and read noise "
            "above the sensor's black level, clipping, 16-bit linear TIFF in the camera's "
            "colour space or 8-bit sRGB PNG, EXIF exposure times. Writes capture.json, the "
            "images and truth.json (the observed profile: the scattering convolved with "
            "the footprint). --preset picks every default at once: 'realistic' (0.04 mm "
            "pixels, 0.03 mm footprint, black level 2048/65535, a 12.8 mm field, P3-D65 "
            "camera) or 'legacy' (the earlier simulator: 0.025 mm pixels, no black level, "
            "Rec.709 camera); the options below override single effects."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="capture-set directory")
    p.add_argument("--preset", choices=["realistic", "legacy"], default="realistic",
                   help="every capture setting at once (docs/ingest.md, Simulator)")
    p.add_argument("--bits", type=int, choices=[8, 16], default=16,
                   help="16 = linear TIFF, 8 = sRGB-encoded PNG")
    p.add_argument("--brackets", type=int, default=5, help="exposures per region (1-9)")
    p.add_argument("--hair", type=int, default=0, help="hair strands across each spot")
    p.add_argument("--hair-clearance-px", type=_float_pair, default=argparse.SUPPRESS,
                   metavar="LO,HI",
                   help="how far the strands' nearest edges pass from the entry point, px "
                        "(below 0: over it; default: the preset's)")
    p.add_argument("--size-px", type=int, default=argparse.SUPPRESS,
                   help="image width and height (default: the preset's)")
    p.add_argument("--mm-per-pixel", type=float, default=argparse.SUPPRESS,
                   help="camera scale (default: the preset's)")
    p.add_argument("--footprint-sigma-mm", type=float, default=argparse.SUPPRESS,
                   help="projector footprint, Gaussian standard deviation (default: the "
                        "preset's; 0: a point)")
    p.add_argument("--black-level", type=float, default=argparse.SUPPRESS,
                   help="sensor offset in 16-bit code values over full scale (0: noise clipped "
                        "at zero; default: the preset's)")
    p.add_argument("--camera-colorspace", default=argparse.SUPPRESS,
                   help="OCIO linear colour space of 16-bit files (default: the preset's)")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--profile", type=Path, nargs="+", default=None, metavar="PROFILE.csv",
                   help="simulate these measured profiles (PROFILE.csv as 'skinpipe fit' "
                        "reads it: radius_mm and ACEScg values in mm^-2, each row the mean "
                        "over a ring reaching halfway to its neighbours) instead of the "
                        "sample subject, one region each, named by the file's stem; "
                        "--camera-colorspace lin_ap1_scene keeps its colours exact")
    add_force_option(p)
    p.set_defaults(handler=cmd_simulate)


def _float_pair(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"need LO,HI (two numbers), got {text!r}") from None
    return lo, hi


def cmd_simulate(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from ..capture.simulate import (
        PRESETS,
        ring_truth,
        sample_subject_truths,
        simulate_capture_set,
    )
    from ..fileio import staged_output_directory

    if not 1 <= args.brackets <= 9:
        raise InputError(f"--brackets must be 1-9, got {args.brackets}")
    preset = PRESETS[args.preset]
    # the effects given on the command line; the rest are the preset's
    overrides = {key: getattr(args, key) for key in (
        "mm_per_pixel", "size_px", "footprint_sigma_mm", "black_level", "hair_clearance_px",
        "camera_colorspace") if hasattr(args, key)}
    settings = replace(preset, bits=args.bits, hair_strands=args.hair,
                       exposures_s=tuple(1 / 500 * 4.0**i for i in range(args.brackets)),
                       image_format="tif" if args.bits == 16 else "png", **overrides)
    truths = sample_subject_truths() if args.profile is None else \
        [ring_truth(path) for path in args.profile]
    with staged_output_directory(args.output, "simulate", args.profile or (), args.force,
                                 ["capture.json", "truth.json"]) as out:
        simulate_capture_set(truths, out.path, settings, seed=args.seed, progress=_eprint)
    print(f"wrote {args.output / 'capture.json'} and {args.output / 'truth.json'}")
    return EXIT_OK
