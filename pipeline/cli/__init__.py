"""The ``skinpipe`` command line: a thin layer over the stage functions.

Results go to stdout, diagnostics and progress to stderr. Exit codes: 0 success,
1 a check failed, 2 bad input or usage.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from .. import __version__
from ..errors import EXIT_BAD_INPUT, EXIT_CHECK_FAILED, EXIT_OK, InputError, SkinpipeError
from . import batch as cli_batch
from . import render_verbs as cli_render
from .render_verbs import _eprint

Handler = Callable[[argparse.Namespace], int]


def _float_list(text: str) -> tuple[float, ...]:
    if text.strip().lower() == "deon":
        from ..profile.reference_data import DEON_2007_SKIN

        return tuple(float(v) for v in DEON_2007_SKIN.variances_mm2)
    try:
        return tuple(float(x) for x in text.split(",") if x.strip())
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from exc


# ----------------------------------------------------------------------------------- fit


def _add_fit(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "fit",
        help="fit a sum of Gaussians to measured radial profiles (CSV -> FIT.json)",
        description=(
            "Fit f(r) = sum_i w_i G(v_i, r) per colour channel, G the normalised 2D Gaussian "
            "(variance v in mm^2, radius r in mm), weights >= 0 summing to 1 per channel "
            "(Park & Oh 2009, eq. 1-2). A genetic algorithm seeds the variances, casadi's IPOPT "
            "refines variances and weights. Error: eq. 2c (relative, r-weighted RMS)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("profiles", nargs="+", type=Path, metavar="PROFILE.csv",
                   help="header and columns radius_mm,R,G,B[,std_R,std_G,std_B]")
    p.add_argument("-k", type=int, default=6, help="Gaussians per variance grid (1-8)")
    p.add_argument("--share", choices=["channels", "none", "profiles"], default="channels",
                   help="curves sharing one variance grid: the 3 channels of a profile, none "
                        "(per channel), or all channels of all PROFILEs (one grid for a face: "
                        "fewer blur passes when rendering)")
    p.add_argument("--fixed-variances", type=_float_list, metavar="V1,V2,...",
                   help="fix the variance grid (mm^2), solve weights only; 'deon' for d'Eon "
                        "et al. 2007's skin grid")
    p.add_argument("--min-radius-mm", type=float, default=0.0,
                   help="leave out samples closer to the entry point (the paper drops them)")
    p.add_argument("--max-radius-mm", type=float, default=None,
                   help="leave out samples farther than this")
    p.add_argument("--free-scale", action="store_true",
                   help="also fit the total diffuse reflectance per channel (absolute captures)")
    p.add_argument("--use-stddev", action="store_true",
                   help="weight samples by 1/std^2 (from std_R,std_G,std_B) besides r dr")
    p.add_argument("--solver", choices=["ipopt", "slsqp"], default="ipopt",
                   help="local refinement after the seed (slsqp = the paper's SQP, for comparison)")
    p.add_argument("--init", choices=["ga", "naive", "random"], default="ga",
                   help="starting point: genetic algorithm, log-spaced grid, or random grid")
    p.add_argument("--generations", type=int, default=40, help="GA generations")
    p.add_argument("--population", type=int, default=32, help="GA population size")
    p.add_argument("--seed", type=int, default=0, help="random seed (GA); same seed, same fit")
    p.add_argument("-o", "--output", type=Path, required=True,
                   help="FIT.json for one profile; a directory (one <name>.json each) for several")
    p.set_defaults(handler=cmd_fit)


def cmd_fit(args: argparse.Namespace) -> int:
    from ..profile.fit import FitOptions, fit_profiles
    from ..profile.io import read_profile_csv, write_fit_json
    fixed = args.fixed_variances or None
    options = FitOptions(
        k=args.k, share=args.share, fixed_variances_mm2=fixed, min_radius_mm=args.min_radius_mm,
        max_radius_mm=args.max_radius_mm, seed=args.seed, generations=args.generations,
        population=args.population, solver=args.solver, init=args.init,
        free_scale=args.free_scale, use_stddev=args.use_stddev,
    )
    profiles = [read_profile_csv(p) for p in args.profiles]
    names = [p.name for p in profiles]
    if len(set(names)) != len(names):
        raise InputError(f"profile names (file stems) must be unique: {names}")
    several = len(profiles) > 1
    if several and args.output.suffix.lower() == ".json":
        raise InputError("several profiles write one JSON each: give -o a directory", args.output)
    if args.share == "profiles" or not several:
        groups = [profiles]
    else:
        groups = [[p] for p in profiles]
    for i, group in enumerate(groups, start=1):
        if several:
            _eprint(f"[{i}/{len(groups)}] fitting {', '.join(p.name for p in group)}")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            results = fit_profiles(group, options)
        for w in caught:
            _eprint(f"warning: {w.message}")
        for res in results:
            target = args.output / f"{res.name}.json" if several else args.output
            write_fit_json(target, res)
            errs = " ".join(f"{c}={e:.2e}" for c, e in zip("RGB", res.error, strict=True))
            print(f"{res.name}: {len(res.variances_mm2)} terms, eq.2c error {errs}, "
                  f"{res.seconds:.2f} s, {res.status} -> {target}")
            for note in res.warnings:
                _eprint(f"note: {res.name}: {note}")
    return EXIT_OK


# -------------------------------------------------------------------------------- ingest


def _add_ingest(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "ingest",
        help="merge bracketed captures to HDR and extract radial profiles (CAPTURES -> CSVs)",
        description=(
            "Read CAPTURES/capture.json (see docs/capture-format.md), merge each region's "
            "brackets into a scene-linear ACEScg HDR image, find the entry point to sub-pixel "
            "accuracy and extract the radial profile per channel in mm. Writes "
            "OUT_DIR/<region>.csv (radius_mm,R,G,B,std_R,std_G,std_B; integrating to 1 over "
            "the measured disk unless --absolute), OUT_DIR/<region>.exr and ingest.json. "
            "Nothing is written unless every region succeeds."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
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
    p.add_argument("--regions", type=lambda t: [x for x in t.split(",") if x], default=None,
                   metavar="A,B", help="only these regions")
    p.set_defaults(handler=cmd_ingest)


def cmd_ingest(args: argparse.Namespace) -> int:
    from ..capture.ingest import IngestOptions, ingest_capture_set

    if not args.ring_width_px > 0:
        raise InputError(f"--ring-width-px must be > 0, got {args.ring_width_px}")
    options = IngestOptions(ring_width_px=args.ring_width_px, max_radius_mm=args.max_radius_mm,
                            mode=args.mode, absolute=args.absolute)
    report = ingest_capture_set(args.captures, args.output, options, progress=_eprint,
                                regions=args.regions)
    for name, entry in report["regions"].items():
        print(f"{name}: {entry['samples']} samples to {entry['max_radius_mm']:.2f} mm "
              f"-> {entry['csv']}")
    return EXIT_OK


def _add_simulate(sub: argparse._SubParsersAction) -> None:
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
    p.set_defaults(handler=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    from ..capture.simulate import CaptureSettings, sample_subject_truths, simulate_capture_set

    if not 1 <= args.brackets <= 9:
        raise InputError(f"--brackets must be 1-9, got {args.brackets}")
    exposures = tuple(1 / 500 * 4.0**i for i in range(args.brackets))
    settings = CaptureSettings(mm_per_pixel=args.mm_per_pixel, size_px=args.size_px,
                               bits=args.bits, exposures_s=exposures, hair_strands=args.hair,
                               image_format="tif" if args.bits == 16 else "png")
    simulate_capture_set(sample_subject_truths(), args.output, settings, seed=args.seed,
                         progress=_eprint)
    print(f"wrote {args.output / 'capture.json'} and {args.output / 'truth.json'}")
    return EXIT_OK


# -------------------------------------------------------------------------------- author


def _add_author(sub: argparse._SubParsersAction) -> None:
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


# ------------------------------------------------------------------------------ validate


def _add_validate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "validate",
        help="check USD assets with USD's validators and skinpipe's rules (for CI)",
        description=(
            "Run OpenUSD's built-in validators (pxr.UsdValidation) and skinpipe's named "
            "rules (registered with the same registry; 'skinpipe validate --list-rules' "
            "documents them) on each file. Prints problems with their sites, then "
            "'Success!' or 'Failed!' like usdchecker. Exit 0 when every file passes, 1 when "
            "a check fails, 2 when a file cannot be read. Text files nested too deep for "
            "USD's parser are refused before parsing."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("assets", nargs="*", type=Path, metavar="ASSET.usd")
    p.add_argument("--strict", action="store_true", help="warnings fail too")
    p.add_argument("--json", action="store_true", help="print a JSON report instead")
    p.add_argument("--junit", type=Path, default=None, metavar="FILE",
                   help="also write a JUnit XML report")
    p.add_argument("--skinpipe-only", action="store_true",
                   help="run only skinpipe's rules, not USD's built-in validators")
    p.add_argument("--list-rules", action="store_true", help="list skinpipe's rules and exit")
    p.set_defaults(handler=cmd_validate)


def cmd_validate(args: argparse.Namespace) -> int:
    from ..fileio import atomic_write_text
    from ..usd.validate import RULES, SKIPPED_BUILTINS, junit_xml, validate_files

    if args.list_rules:
        for r in RULES:
            print(f"{r.name}\n    {r.doc}")
        for name, why in SKIPPED_BUILTINS.items():
            print(f"(skipped built-in) {name}\n    {why}")
        return EXIT_OK
    if not args.assets:
        raise InputError("no ASSET.usd given")
    reports = validate_files(args.assets, include_builtin=not args.skinpipe_only)
    if args.junit:
        atomic_write_text(args.junit, junit_xml(reports, args.strict))
    unreadable = any(r.unreadable is not None for r in reports)
    failed = any(r.failed(args.strict) for r in reports)
    if args.json:
        print(json.dumps([{"file": r.path, "unreadable": r.unreadable,
                           "seconds": round(r.seconds, 4),
                           "result": "Failed" if r.failed(args.strict) else "Success",
                           "problems": [p.__dict__ | {"sites": list(p.sites)}
                                        for p in r.problems]} for r in reports], indent=2))
    else:
        for r in reports:
            if r.unreadable is not None:
                _eprint(f"{r.path}: cannot read: {r.unreadable}")
            for prob in r.problems:
                print(f"{r.path}: [{prob.rule}] {prob.severity}: {prob.message} "
                      f"({', '.join(prob.sites)})")
        print("Failed!" if failed else "Success!")
    if unreadable:
        return EXIT_BAD_INPUT
    return EXIT_CHECK_FAILED if failed else EXIT_OK


# ------------------------------------------------------------------------------- inspect


def _add_inspect(sub: argparse._SubParsersAction) -> None:
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

    stage = open_stage_guarded(args.asset)
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


def _add_env(sub: argparse._SubParsersAction) -> None:
    from .render_verbs import add_device_option

    p = sub.add_parser(
        "env",
        help="print the PXR_PLUGINPATH_NAME line and the OpenCL device skinpipe uses",
        description="Print the shell line that makes usdview or a DCC see skinpipe's USD "
                    "schema and usdview plugin (add it to your shell profile or launcher), "
                    "then every OpenCL device found, probed with a kernel that uses what "
                    "skinpipe's kernels use: the one chosen, and why each other one was "
                    "not (one line each, on stderr as comments).",
    )
    add_device_option(p)
    p.set_defaults(handler=cmd_env)


def cmd_env(args: argparse.Namespace) -> int:
    from ..render.opencl import choose_device, device_spec, set_device
    from ..render.opencl_runtimes import SETUP
    from ..usd.schema import pxr_plugin_path_line

    print(pxr_plugin_path_line())
    if args.device:
        set_device(args.device)
    choice = choose_device(device_spec(), probe_all=True)
    _eprint(f"# OpenCL device ('{choice.spec}'): {choice.candidate.label} "
            f"[{choice.candidate.runtime}]"
            + ("" if choice.nontemporal_stores else " (without streaming stores)"))
    for cand, reason in choice.tried:
        if cand != choice.candidate:
            _eprint(f"#   not used: {cand.label} [{cand.runtime}]: {reason}")
    for note in SETUP.notes:
        _eprint(f"#   note: {note}")
    return EXIT_OK


# ---------------------------------------------------------------------------------- demo


def sample_captures_dir() -> Path:
    """The bundled sample capture set (in the source tree beside the package)."""
    return Path(__file__).resolve().parents[2] / "sample_assets" / "captures"


def _add_demo(sub: argparse._SubParsersAction) -> None:
    from .render_verbs import add_render_options

    p = sub.add_parser(
        "demo",
        help="run the whole pipeline on the bundled sample assets",
        description=(
            "Ingest the bundled six-region sample captures (sample_assets/captures), fit each "
            "region's profile with a sum of Gaussians, compare both with the simulator's "
            "known truth, author a USD asset on pymeshlab's real face scan with the six "
            "regions placed by sample_assets/face/landmarks.json, paint it a skin albedo "
            "(regional tones, freckles, moles), validate it, and render it with its six "
            "profiles; then the paper's figure 7 (texture-mapped only vs with scattering) "
            "and per-region vs one profile, side by side. Writes OUT/profiles, OUT/fits, "
            "OUT/asset, OUT/scene.usda, OUT/render (EXR, PNG, render.json) and "
            "OUT/report.json (each stage's seconds and error)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("-o", "--output", type=Path, default=Path("demo_out"), help="output directory")
    p.add_argument("-k", type=int, default=6, help="Gaussians per profile")
    add_render_options(p, resolution="768x768", texture_size=1024)
    p.set_defaults(handler=cmd_demo)


def cmd_demo(args: argparse.Namespace) -> int:
    from ..capture.simulate import read_truth
    from ..fileio import atomic_write_json
    from ..usd.mesh import pymeshlab_face_scan
    from .render_verbs import ocio_source, render_options, run_chain

    captures = sample_captures_dir()
    if not (captures / "capture.json").is_file():
        raise InputError("the sample assets are missing (run from a clone of the repository)",
                         captures)
    out = args.output
    options = render_options(args)
    report = run_chain(captures, pymeshlab_face_scan(), captures.parent / "face" /
                       "landmarks.json", out, args.k, True, True, options, ocio_source(args),
                       truth=read_truth(captures / "truth.json"), comparisons=True)
    atomic_write_json(out / "report.json", report)
    print(f"wrote {out / 'report.json'} ({report['total_seconds']:.1f} s)")
    return EXIT_OK if report["valid"] else EXIT_CHECK_FAILED


# -------------------------------------------------------------------------------- report


def _add_report(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "report",
        help="error against run time per stage (JSON + PNG, gathered on one report.md page)",
        description=(
            "Measure a stage's error/time trade-off in one run so that users can pick an "
            "operating point. 'fit': k = 1..8 with GA+IPOPT (default), IPOPT from a naive "
            "start, and GA+SLSQP (the paper's SQP), on the given profiles or, without any, "
            "on reference profiles (d'Eon et al. 2007 skin, Jensen et al. 2001 dipoles). "
            "'ingest': simulated captures with 1, 3, 5, 7 brackets and ring widths 0.5-4 px, "
            "profile error against the simulator's truth beside ingest time. "
            "'render SCENE': texture sizes (--sizes) x variance grids (--grids), the "
            "diffused radiance against a brute-force convolution on the surface with the "
            "exact per-region profiles, beside texture-map + irradiance + diffusion time "
            "(--blurs recursive,gather compares the diffusion blurs). 'all SCENE': the three. "
            "Every run also (re)writes OUTPUT/report.md, one page with each stage found in "
            "OUTPUT: plot, table, Pareto front, and whether the default sits on it."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("stage", choices=["fit", "ingest", "render", "all"],
                   help="which stage to measure ('all': fit, ingest and render)")
    p.add_argument("profiles", nargs="*", type=Path, metavar="PROFILE.csv|SCENE",
                   help="fit: profiles to fit (default: built-in reference profiles); "
                        "render and all: the scene (e.g. demo_out/scene.usda)")
    p.add_argument("--sizes", type=lambda t: [int(x) for x in t.split(",")],
                   default=[512, 1024, 2048], metavar="N,N",
                   help="render: texture sizes (4096 works, needs minutes and ~6 GiB)")
    p.add_argument("--grids", type=lambda t: [int(x) for x in t.split(",")],
                   default=[0, 8, 12], metavar="N,N",
                   help="render: variance grids (0 = each region's own variances)")
    p.add_argument("--blurs", type=lambda t: [b.strip() for b in t.split(",")],
                   default=["recursive"], metavar="B,B",
                   help="render: diffusion blurs to compare (recursive, gather)")
    p.add_argument("--k", type=_int_range, default=(1, 8), metavar="A:B",
                   help="range of k to try, inclusive")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.set_defaults(handler=cmd_report)


def _int_range(text: str) -> tuple[int, int]:
    try:
        a, _, b = text.partition(":")
        lo, hi = int(a), int(b or a)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected A:B, got {text!r}") from exc
    if not 1 <= lo <= hi <= 8:
        raise argparse.ArgumentTypeError(f"need 1 <= A <= B <= 8, got {text!r}")
    return lo, hi


def _report_render(args: argparse.Namespace, scene: Path) -> None:
    from ..workflow.report import render_tradeoff, write_render_report

    rows = render_tradeoff(scene, args.sizes, args.grids, progress=_eprint, blurs=args.blurs)
    doc = write_render_report(rows, args.output)
    print(f"{'texture':>7} {'grid':>4} {'blur':>9} {'mm/texel':>8} {'passes':>6} {'seconds':>8} "
          f"{'diffuse s':>9} {'error':>9}  pareto")
    for r in doc["rows"]:
        print(f"{r['texture_size']:>7} {r['variance_grid']:>4} {r['blur']:>9} "
              f"{r['mm_per_texel']:>8.3f} {r['blur_passes']:>6} {r['seconds']:>8.2f} "
              f"{r['diffusion_seconds']:>9.2f} {r['error_max']:>9.2e}  "
              f"{'*' if r['pareto'] else ''}")


def _report_ingest(args: argparse.Namespace) -> None:
    import tempfile

    from ..workflow.report import ingest_tradeoff, write_ingest_report

    with tempfile.TemporaryDirectory(prefix="skinpipe-report-") as work:
        rows = ingest_tradeoff(Path(work), progress=_eprint)
    write_ingest_report(rows, args.output)
    print(f"{'region':<10} {'brackets':>8} {'ring px':>7} {'seconds':>8} {'error':>9}")
    for r in rows:
        print(f"{r['region']:<10} {r['brackets']:>8} {r['ring_width_px']:>7g} "
              f"{r['seconds']:>8.3f} {r['error_max']:>9.2e}")


def _report_fit(args: argparse.Namespace, profile_paths: list[Path]) -> None:
    from ..profile.io import read_profile_csv
    from ..workflow.report import fit_tradeoff, write_fit_report

    profiles = ([read_profile_csv(p) for p in profile_paths] if profile_paths
                else _reference_profiles())
    rows = fit_tradeoff(profiles, ks=range(args.k[0], args.k[1] + 1), progress=_eprint)
    doc = write_fit_report(rows, args.output)
    print(f"{'profile':<16} {'method':<12} {'k':>2} {'seconds':>8} {'error':>9}  pareto")
    for row in doc["rows"]:
        print(f"{row['profile']:<16} {row['method']:<12} {row['k']:>2} {row['seconds']:>8.3f} "
              f"{row['error_max']:>9.2e}  {'*' if row['pareto'] else ''}")


def cmd_report(args: argparse.Namespace) -> int:
    from ..workflow.report import write_report_page

    scenes = [p for p in args.profiles if p.suffix in (".usd", ".usda", ".usdc", ".usdz")]
    if args.stage in ("render", "all"):
        if len(scenes) != 1:
            raise InputError(f"report {args.stage} needs exactly one SCENE (.usd/.usda/.usdc)")
        scene = scenes[0]
        if not scene.is_file():
            raise InputError("scene not found", scene)
    if args.stage in ("fit", "all"):
        _report_fit(args, [p for p in args.profiles if p not in scenes])
    if args.stage in ("ingest", "all"):
        _report_ingest(args)
    if args.stage in ("render", "all"):
        _report_render(args, scene)
    page = write_report_page(args.output)
    print(f"wrote {args.stage} trade-off JSON and PNG into {args.output}; page: {page}")
    return EXIT_OK


def _reference_profiles() -> list:
    import numpy as np

    from ..profile.fit import MeasuredProfile
    from ..profile.models import dipole_profile, dipole_total_reflectance, sum_of_gaussians
    from ..profile.reference_data import DEON_2007_SKIN, JENSEN_2001

    r = np.linspace(0.0, 4.0, 200)
    out = [MeasuredProfile(r, sum_of_gaussians(DEON_2007_SKIN.variances_mm2,
                                               DEON_2007_SKIN.weights, r), name="deon2007")]
    for name in ("skin1", "skin2"):
        c = JENSEN_2001[name]
        out.append(MeasuredProfile(r, dipole_profile(r, c) / dipole_total_reflectance(c),
                                   name=f"dipole_{name}"))
    return out


# ------------------------------------------------------------------------------ parser


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="skinpipe",
        description=(
            "Measured skin scattering to production assets: ingest bracketed captures of a "
            "lit skin point, fit sum-of-Gaussians diffusion profiles, author USD assets, "
            "render faces with texture-space diffusion. "
            "Radii in mm, variances in mm^2. Run 'skinpipe VERB --help' for each verb."
        ),
        epilog="Exit codes: 0 success, 1 a check failed, 2 bad input or usage.",
    )
    parser.add_argument("--version", action="version", version=f"skinpipe {__version__}")
    sub = parser.add_subparsers(dest="verb", metavar="VERB", required=True)
    for add in _VERBS:
        add(sub)
    return parser


_VERBS: list[Callable[[argparse._SubParsersAction], None]] = [
    _add_demo, _add_ingest, _add_fit, _add_author, _add_validate, _add_inspect,
    cli_render.add_paint_albedo, cli_render.add_shot, cli_render.add_render, cli_render.add_run,
    cli_batch.add_batch,
    _add_report, _add_simulate, _add_env,
]


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: 0 for --help, 2 for usage errors
        return int(exc.code or 0)
    handler: Handler = args.handler
    try:
        return handler(args)
    except InputError as exc:
        _eprint(f"skinpipe {args.verb}: error: {exc}")
        return EXIT_BAD_INPUT
    except SkinpipeError as exc:
        _eprint(f"skinpipe {args.verb}: failed: {exc}")
        return EXIT_CHECK_FAILED
    except KeyboardInterrupt:
        _eprint(f"skinpipe {args.verb}: interrupted; no partial output was kept")
        return 130


if __name__ == "__main__":
    sys.exit(main())
