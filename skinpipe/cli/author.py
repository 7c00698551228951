"""``skinpipe author``: fits and a mesh to a USD asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK
from .common import HelpFormatter, _eprint, add_force_option


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "author",
        help="write fitted profiles and a face mesh into a USD asset",
        description=(
            "Write ASSET_DIR/asset.usda (defaultPrim, kind component, metersPerUnit, upAxis, "
            "colour space), geo.usdc (mesh, region primvars, GeomSubsets, "
            "SkinProfileRegionsAPI) and look.usda (SkinDiffusionProfile prims under Looks, a "
            "UsdPreviewSurface material and an approximate OpenPBR one). Regions come from a "
            "landmarks file (soft borders) or from an existing uniform int primvar of a USD "
            "mesh. Layers are written to temporary files and renamed; inputs are only read."
        ),
        formatter_class=HelpFormatter,
    )
    p.add_argument("--fits", nargs="+", type=Path, required=True, metavar="DIR_OR_JSON",
                   help="FIT.json files or directories of them; each fit's name is its region")
    p.add_argument("--mesh", type=Path, required=True,
                   help="face mesh: USD (first Mesh, or --mesh-prim), PLY or OBJ")
    p.add_argument("--mesh-prim", default=None, help="Mesh prim path inside a USD mesh file")
    p.add_argument("--landmarks", type=Path, default=None,
                   help="JSON {'regions': {name: [[x, y, z], ...]}} in mesh units")
    p.add_argument("--region-primvar", default=None, metavar="NAME",
                   help="take regions from this uniform int primvar of a USD mesh instead")
    p.add_argument("--region-names", type=lambda t: [x for x in t.split(",") if x],
                   default=None, metavar="A,B",
                   help="region names for the values 0, 1, ... of --region-primvar")
    p.add_argument("--blend-mm", type=float, default=8.0,
                   help="width of the soft border between landmark regions, mm")
    p.add_argument("--profiles", type=Path, default=None, metavar="DIR",
                   help="ingest output with <region>.csv measured samples to embed "
                        "(default: each fit's source CSV, when it exists)")
    p.add_argument("--meters-per-unit", type=float, default=None,
                   help="scene unit of a PLY/OBJ mesh (default 0.001: millimetres)")
    p.add_argument("--prepare-scan", action="store_true",
                   help="clean a raw range scan first (pymeshlab: merge, keep the largest "
                        "piece, close the holes inside it, decimate to --target-faces) "
                        "and seal its open rim with a Geom/Seal occluder")
    p.add_argument("--target-faces", type=int, default=60000, help="with --prepare-scan")
    p.add_argument("--name", default="Face", help="asset (and default prim) name")
    p.add_argument("-o", "--output", type=Path, required=True, help="asset directory")
    add_force_option(p)
    p.set_defaults(handler=cmd_author)


def cmd_author(args: argparse.Namespace) -> int:
    from ..fileio import staged_output_directory
    from ..usd.author import ASSET_FILES
    from ..workflow.chain import author_from_files, author_inputs

    reads = author_inputs(args.fits, args.mesh, args.landmarks, args.profiles)
    with staged_output_directory(args.output, "author", reads, args.force,
                                 ASSET_FILES) as out:
        paths = author_from_files(
            args.fits, args.mesh, out.path, landmarks=args.landmarks,
        region_primvar=args.region_primvar, region_names=args.region_names,
        blend_mm=args.blend_mm, profiles_dir=args.profiles,
        meters_per_unit=args.meters_per_unit, prepare=args.prepare_scan,
            target_faces=args.target_faces, name=args.name, mesh_prim=args.mesh_prim,
            progress=_eprint)
    paths = out.final(paths)
    print(f"wrote {paths.asset} (+ {paths.geo.name}, {paths.look.name}) in {paths.seconds:.2f} s")
    return EXIT_OK
