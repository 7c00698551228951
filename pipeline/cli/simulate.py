"""``skinpipe simulate``: capture sets with known truth from the simulator."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="write a physically simulated capture set with known true profiles",
        description=(
            "Render single-pixel scattering captures of the six face regions of a sample "
            "subject (forehead from Park & Oh 2009; the others from Jensen et al. 2001's "
            "measured skin coefficients, varied per region): projector footprint, pixel "
            "integration, hair strands, photon and read noise, clipping, 8-bit sRGB or "
            "16-bit linear encoding, EXIF exposure times. Writes capture.json, the images "
            "and truth.json."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("-o", "--output", type=Path, required=True, help="capture-set directory")
    p.add_argument("--bits", type=int, choices=[8, 16], default=16,
                   help="16 = linear TIFF, 8 = sRGB-encoded PNG")
    p.add_argument("--brackets", type=int, default=5, help="exposures per region (1-9)")
    p.add_argument("--hair", type=int, default=0, help="hair strands across each spot")
    p.add_argument("--size-px", type=int, default=320, help="image width and height")
    p.add_argument("--mm-per-pixel", type=float, default=0.025, help="camera scale")
    p.add_argument("--seed", type=int, default=0, help="random seed")
    add_force_option(p)
    p.set_defaults(handler=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..capture.simulate import CaptureSettings, sample_subject_truths, simulate_capture_set
    from ..fileio import staged_output_directory

    if not 1 <= args.brackets <= 9:
        raise InputError(f"--brackets must be 1-9, got {args.brackets}")
    exposures = tuple(1 / 500 * 4.0**i for i in range(args.brackets))
    settings = CaptureSettings(mm_per_pixel=args.mm_per_pixel, size_px=args.size_px,
                               bits=args.bits, exposures_s=exposures, hair_strands=args.hair,
                               image_format="tif" if args.bits == 16 else "png")
    with staged_output_directory(args.output, "simulate", (), args.force,
                                 ["capture.json", "truth.json"]) as out:
        simulate_capture_set(sample_subject_truths(), out.path, settings, seed=args.seed,
                             progress=_eprint)
    print(f"wrote {args.output / 'capture.json'} and {args.output / 'truth.json'}")
    return EXIT_OK
