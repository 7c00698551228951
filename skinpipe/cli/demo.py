"""``skinpipe demo``: the whole chain on the bundled sample assets."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError
from ..package_data import package_folder
from .common import (
    HelpFormatter,
    add_force_option,
    add_render_options,
)


def sample_captures_dir() -> Path:
    """The bundled sample capture set (package data)."""
    return package_folder("samples") / "captures"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="run the whole skinpipe on the bundled sample assets",
        description=(
            "Ingest the bundled six-region sample captures (skinpipe/samples/captures), fit each "
            "region's profile with a sum of Gaussians, compare both with the simulator's "
            "known truth, author a USD asset on pymeshlab's real face scan with the six "
            "regions placed by skinpipe/samples/face/landmarks.json, paint it a skin albedo "
            "(regional tones, freckles, moles), validate it, and render it with its six "
            "profiles; then the paper's figure 7 (texture-mapped only vs with scattering) "
            "and per-region vs one profile, side by side. Writes OUT/profiles, OUT/fits, "
            "OUT/asset, OUT/scene.usda, OUT/render (EXR, PNG, render.json) and "
            "OUT/report.json (each stage's seconds and error)."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("-o", "--output", type=Path, default=Path("demo_out"), help="output directory")
    p.add_argument("-k", type=int, default=6, help="Gaussians per profile")
    add_render_options(p, resolution="768x768", texture_size=1024)
    add_force_option(p)
    p.set_defaults(handler=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from ..capture.simulate import read_truth
    from ..usd.mesh import pymeshlab_face_scan
    from .run import run_staged

    captures = sample_captures_dir()
    if not (captures / "capture.json").is_file():
        raise InputError("the sample captures are missing from this installation "
                         "(reinstall skinpipe with pip)", captures)
    return run_staged(args, "demo", captures, pymeshlab_face_scan(),
                      captures.parent / "face" / "landmarks.json", True, True,
                      truth=read_truth(captures / "truth.json"))
