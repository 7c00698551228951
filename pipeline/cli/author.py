"""``skinpipe author``: fits and a mesh to a USD asset."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import EXIT_OK, InputError
from .common import _eprint


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
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
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
    p.set_defaults(handler=cmd_author)


def _measured_for(fits: list, profiles_dir: Path | None) -> dict:
    from ..profile.io import read_profile_csv

    out = {}
    for fit in fits:
        if profiles_dir is not None:
            csv: Path | None = profiles_dir / f"{fit.name}.csv"
        else:
            csv = Path(fit.source) if fit.source else None
        if csv is not None and csv.is_file():
            out[fit.name] = read_profile_csv(csv, name=fit.name)
    return out


def author_from_args(fits_paths: list[Path], mesh_path: Path, out: Path, *,
                     landmarks: Path | None = None, region_primvar: str | None = None,
                     region_names: list[str] | None = None, blend_mm: float = 8.0,
                     profiles_dir: Path | None = None, meters_per_unit: float | None = None,
                     prepare: bool = False, target_faces: int = 60000, name: str = "Face",
                     mesh_prim: str | None = None):
    """The author verb as a function (the demo calls it too)."""
    import numpy as np

    from ..profile.io import read_fit_inputs
    from ..usd.author import (
        RegionAssignment,
        assign_regions_from_landmarks,
        author_asset,
        read_landmarks,
    )
    from ..usd.mesh import load_mesh, prepare_scan, seal_scan

    fits = read_fit_inputs(fits_paths)
    mesh = load_mesh(mesh_path, meters_per_unit, mesh_prim)
    seal = None
    if prepare:
        _eprint(f"preparing the scan ({mesh.n_faces} faces -> {target_faces})")
        mesh = prepare_scan(mesh, target_faces)
        seal = seal_scan(mesh)
    if landmarks is not None:
        regions = assign_regions_from_landmarks(mesh, read_landmarks(landmarks), blend_mm)
    elif region_primvar is not None:
        from pxr import UsdGeom

        from ..usd.io import open_stage_guarded

        stage = open_stage_guarded(mesh_path)
        prim = stage.GetPrimAtPath(mesh_prim) if mesh_prim else next(
            p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
        pv = UsdGeom.PrimvarsAPI(prim).GetPrimvar(region_primvar)
        if not pv or not pv.HasValue() or pv.GetInterpolation() != UsdGeom.Tokens.uniform:
            raise InputError(f"no uniform primvar {region_primvar!r} on {prim.GetPath()}",
                             mesh_path)
        idx = np.asarray(pv.Get(), dtype=np.int32)
        if not region_names:
            raise InputError("--region-primvar needs --region-names A,B,... (one per value)")
        if idx.size != mesh.n_faces or idx.min() < 0 or idx.max() >= len(region_names):
            raise InputError(f"{region_primvar} must hold one index in 0..{len(region_names) - 1}"
                             f" per face ({mesh.n_faces} faces)", mesh_path)
        regions = RegionAssignment(tuple(region_names), idx)
    else:
        raise InputError("give --landmarks or --region-primvar to place the regions")
    return author_asset(fits, mesh, regions, out, name=name,
                        measured=_measured_for(fits, profiles_dir), seal=seal)


def cmd_author(args: argparse.Namespace) -> int:
    paths = author_from_args(
        args.fits, args.mesh, args.output, landmarks=args.landmarks,
        region_primvar=args.region_primvar, region_names=args.region_names,
        blend_mm=args.blend_mm, profiles_dir=args.profiles,
        meters_per_unit=args.meters_per_unit, prepare=args.prepare_scan,
        target_faces=args.target_faces, name=args.name, mesh_prim=args.mesh_prim)
    print(f"wrote {paths.asset} (+ {paths.geo.name}, {paths.look.name}) in {paths.seconds:.2f} s")
    return EXIT_OK
