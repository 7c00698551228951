"""``skinpipe`` verbs of the render stage: shot, paint-albedo, render, run (and the
render half of the demo). A thin layer over :mod:`pipeline.render.renderer`."""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..errors import EXIT_OK, InputError


def _eprint(*args: object) -> None:
    print(*args, file=sys.stderr, flush=True)


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, _, h = text.lower().partition("x")
        return int(w), int(h or w)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from exc


def _frames(text: str) -> tuple[int, int]:
    try:
        a, _, b = text.partition(":")
        lo, hi = int(a), int(b or a)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected A:B, got {text!r}") from exc
    if lo > hi or hi - lo > 10000:
        raise argparse.ArgumentTypeError(f"need A <= B (at most 10000 frames), got {text!r}")
    return lo, hi


def _aovs(text: str) -> tuple[str, ...]:
    return tuple(a.strip() for a in text.split(",") if a.strip())


def add_render_options(p: argparse.ArgumentParser, resolution: str = "1024x1024",
                       texture_size: int = 1024) -> None:
    from ..render.renderer import AOVS, BLURS, SHADOW_SAMPLING

    p.add_argument("--camera", default=None, metavar="PRIM",
                   help="UsdGeomCamera prim path (default: the first camera on the stage)")
    p.add_argument("--resolution", type=_resolution, default=_resolution(resolution),
                   metavar="WxH", help=f"image size in pixels (default {resolution})")
    p.add_argument("--texture-size", type=int, default=texture_size, metavar="N",
                   help="texture-space maps are N x N texels")
    p.add_argument("--aovs", type=_aovs, default=AOVS, metavar="A,B",
                   help=f"AOVs to write, from {','.join(AOVS)} (default: all)")
    p.add_argument("--light-samples", type=int, default=16,
                   help="stratified light samples per texel and light (area and dome lights; "
                        "see --shadow-sampling for how many are traced)")
    p.add_argument("--shadow-sampling", choices=SHADOW_SAMPLING, default="interleaved",
                   help="interleaved: each texel traces a quarter of the light samples and "
                        "borrows the rest from its 3x3 neighbours (Keller & Heidrich 2001; "
                        "4x fewer rays, same error measured on the demo face); full: every "
                        "texel traces all of them")
    p.add_argument("--variance-grid", type=int, default=12, metavar="N",
                   help="re-express all regions' profiles on N shared variances (fewer "
                        "blurs; the error is in render.json); 0 = each region's own")
    p.add_argument("--blur", choices=BLURS, default="recursive",
                   help="diffusion blur: recursive Gaussian on a pyramid (cost independent "
                        "of width) or the per-tap gather kernel (cost grows with width)")
    p.add_argument("--no-scattering", action="store_true",
                   help="texture-mapped irradiance only (no subsurface diffusion)")
    p.add_argument("--single-profile", default=None, metavar="mean|REGION",
                   help="one profile for the whole face instead of one per region")
    p.add_argument("--albedo-split", type=float, default=0.5,
                   help="albedo exponent applied before scattering (0.5 = sqrt before/after)")
    p.add_argument("--roughness", type=float, default=0.35, help="Beckmann roughness")
    p.add_argument("--rho-s", type=float, default=0.25, help="specular scale rho_s")
    p.add_argument("--no-write-uvs", action="store_true",
                   help="do not write xatlas UVs back into the asset's geo layer")
    p.add_argument("--ocio", default=None,
                   help="OCIO config for the display PNG (default: $OCIO, else "
                        "ocio://default)")
    add_device_option(p)


def add_device_option(p: argparse.ArgumentParser) -> None:
    from ..render.opencl import DEVICE_HELP

    p.add_argument("--device", default=None, metavar="SPEC", help=DEVICE_HELP)


def render_options(args: argparse.Namespace) -> Any:
    from ..render.renderer import RenderOptions

    return RenderOptions(
        resolution=args.resolution, texture_size=args.texture_size, aovs=args.aovs,
        light_samples=args.light_samples, shadow_sampling=args.shadow_sampling,
        roughness=args.roughness, rho_s=args.rho_s,
        albedo_split=args.albedo_split, variance_grid=args.variance_grid,
        scattering=not args.no_scattering, blur=args.blur, single_profile=args.single_profile,
        camera=args.camera, write_uvs=not args.no_write_uvs, device=args.device)


def ocio_source(args: argparse.Namespace) -> str:
    return args.ocio or os.environ.get("OCIO") or "ocio://default"


def _print_render(doc: dict[str, Any]) -> None:
    for frame in doc["frames"]:
        tasks = ", ".join(f"{k} {v:.2f} s" for k, v in frame["tasks"].items())
        label = "" if frame["frame"] is None else f"frame {frame['frame']}: "
        print(f"{label}{frame['outputs']['exr']} ({frame['seconds']:.1f} s: {tasks}"
              f"{'; cached ' + ', '.join(frame['cached']) if frame['cached'] else ''})")
        diff = frame["measures"].get("diffusion", {})
        if diff:
            print(f"  diffusion: {len(diff['variances_mm2'])} variances, "
                  f"{diff['blur_passes']} blur passes, energy ratio "
                  f"{diff['energy_ratio']:.4f}, grid error (eq. 2c) max "
                  f"{max(diff['grid_error_eq2c'].values()):.2e}")


# ---------------------------------------------------------------------------- render


def add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render",
        help="render a USD scene with texture-space subsurface diffusion",
        description=(
            "Render SCENE (an asset with skin profiles, plus a camera and UsdLux lights; "
            "'skinpipe shot' makes such a layer): xatlas UVs where the mesh has none "
            "(written back into the asset's geo layer), texture maps, irradiance with "
            "Embree shadow rays, OpenCL diffusion with the fitted profiles, "
            "Torrance-Sparrow specular. Writes OUT/<name>.exr (ACEScg, one layer per AOV), "
            "OUT/<name>.png (display view through OCIO) and OUT/render.json (each task's "
            "seconds, what was cached or skipped, error measures). With --frames, one pair "
            "per frame; texture-space work is reused while only the camera moves."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="USD scene or asset to render")
    add_render_options(p)
    p.add_argument("--frames", type=_frames, default=None, metavar="A:B",
                   help="render time codes A..B (e.g. a turntable from 'skinpipe shot')")
    p.add_argument("--name", default=None, help="image name (default: the scene's stem)")
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.set_defaults(handler=cmd_render)


def cmd_render(args: argparse.Namespace) -> int:
    from ..render.renderer import render_files

    doc = render_files(args.scene, args.output, render_options(args), args.frames,
                       ocio_source(args), args.name, progress=_eprint)
    _print_render(doc)
    print(f"wrote {args.output / 'render.json'} ({doc['total_seconds']:.1f} s)")
    return EXIT_OK


# ------------------------------------------------------------------------------ shot


def add_shot(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "shot",
        help="write a shot layer (camera, key and fill light) over an asset",
        description=(
            "Write OUT (.usda) that sublayers ASSET and adds /Shot/Camera framing the "
            "asset from the front (+Z, Y up), a key SphereLight (soft shadows) and a dim "
            "DomeLight fill. The asset is only read."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("asset", type=Path)
    p.add_argument("--turntable", type=int, default=0, metavar="N",
                   help="animate the camera once around the asset over frames 1..N")
    p.add_argument("--key-intensity", type=float, default=3.0,
                   help="irradiance the key light gives a surface facing it")
    p.add_argument("--fill-intensity", type=float, default=0.15, help="dome radiance")
    p.add_argument("-o", "--output", type=Path, required=True, help="shot layer to write")
    p.set_defaults(handler=cmd_shot)


def cmd_shot(args: argparse.Namespace) -> int:
    from ..usd.shot import ShotOptions, author_shot

    out = author_shot(args.asset, args.output, ShotOptions(
        key_intensity=args.key_intensity, fill_intensity=args.fill_intensity,
        turntable_frames=args.turntable))
    print(f"wrote {out}")
    return EXIT_OK


# ---------------------------------------------------------------------- paint-albedo


def add_paint_albedo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "paint-albedo",
        help="paint a plausible skin albedo texture on an asset that has none",
        description=(
            "For an asset without colour (like the sample face scan): unwrap the skin mesh "
            "if it has no usable UVs (written back into its geo layer), paint a tone per "
            "region with freckles and moles (sizes in mm on the surface), write "
            "albedo.exr (ACEScg) beside the asset and bind it to the material's "
            "diffuseColor. Changes the asset's geo and look layers in place (atomically)."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("asset", type=Path)
    p.add_argument("--size", type=int, default=2048, help="texture size in texels")
    p.add_argument("--seed", type=int, default=7, help="freckle and mole placement")
    p.set_defaults(handler=cmd_paint_albedo)


def cmd_paint_albedo(args: argparse.Namespace) -> int:
    from ..render.albedo import bake_sample_albedo

    print(f"wrote {bake_sample_albedo(args.asset, args.size, args.seed, _eprint)}")
    return EXIT_OK


# ------------------------------------------------------------------------------- run


def add_run(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="ingest, fit, author and render in one go",
        description=(
            "Chain the stages on one capture set: ingest CAPTURES into OUT/profiles, fit "
            "each region into OUT/fits, author OUT/asset on MESH (regions from "
            "--landmarks), optionally paint a sample albedo, write the shot layer "
            "OUT/scene.usda and render it into OUT/render."
        ),
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("captures", type=Path, help="capture set directory (capture.json)")
    p.add_argument("--mesh", type=Path, required=True, help="face mesh (USD, PLY, OBJ)")
    p.add_argument("--landmarks", type=Path, required=True, help="region landmarks JSON")
    p.add_argument("--prepare-scan", action="store_true", help="clean/decimate a raw scan")
    p.add_argument("--paint-albedo", action="store_true",
                   help="paint the procedural skin albedo (for meshes without colour)")
    p.add_argument("-k", type=int, default=6, help="Gaussians per profile")
    add_render_options(p)
    p.add_argument("-o", "--output", type=Path, required=True, help="output directory")
    p.set_defaults(handler=cmd_run)


def run_chain(captures: Path, mesh: Path, landmarks: Path, out: Path, k: int,
              prepare: bool, paint: bool, options: Any, ocio: str,
              truth: dict[str, Any] | None = None, comparisons: bool = False
              ) -> dict[str, Any]:
    """ingest -> fit -> author -> (paint) -> shot -> render (-> the demo's comparison
    renders, which reuse the render's texture-space work); returns the report."""
    from ..capture.ingest import ingest_capture_set
    from ..profile.fit import FitOptions, fit_sum_of_gaussians
    from ..profile.io import read_profile_csv, write_fit_json
    from ..render.renderer import Renderer, render_files
    from ..usd.io import open_stage_guarded
    from ..usd.shot import author_shot
    from ..usd.validate import validate_file
    from . import author_from_args

    start = time.perf_counter()
    report: dict[str, Any] = {"stages": {}, "regions": {}}
    _eprint(f"ingest {captures}")
    ingest = ingest_capture_set(captures, out / "profiles", progress=_eprint)
    report["stages"]["ingest"] = {"seconds": time.perf_counter() - start}
    fit_s = 0.0
    print(f"{'region':<10} {'terms':>5} {'fit err (eq.2c)':>16} {'vs truth':>9} {'fit s':>6}")
    for name, entry in ingest["regions"].items():
        prof = read_profile_csv(entry["csv"])
        # Ingested profiles integrate to 1 over the image's disk only: fit the scale too.
        fit = fit_sum_of_gaussians(prof, FitOptions(k=k, free_scale=True))
        write_fit_json(out / "fits" / f"{name}.json", fit)
        fit_s += fit.seconds
        row: dict[str, Any] = {"ingest_seconds": entry["seconds"], "fit_seconds": fit.seconds,
                               "fit_error": fit.error.tolist(),
                               "fit": str(out / "fits" / f"{name}.json")}
        vs = "-"
        if truth and name in truth:
            err = truth[name].profile_error(prof.radius_mm, fit.evaluate(prof.radius_mm))
            row["error_vs_truth"] = err.tolist()
            vs = f"{err.max():.2e}"
        report["regions"][name] = row
        print(f"{name:<10} {len(fit.variances_mm2):>5} {fit.error.max():>16.2e} {vs:>9} "
              f"{fit.seconds:>6.2f}")
    report["stages"]["fit"] = {"seconds": fit_s}
    t0 = time.perf_counter()
    _eprint(f"author {out / 'asset'}")
    paths = author_from_args([out / "fits"], mesh, out / "asset", landmarks=landmarks,
                             profiles_dir=out / "profiles", prepare=prepare)
    report["stages"]["author"] = {"seconds": time.perf_counter() - t0, "asset": str(paths.asset)}
    if paint:
        from ..render.albedo import bake_sample_albedo

        t0 = time.perf_counter()
        texture = bake_sample_albedo(paths.asset, options.texture_size, progress=_eprint)
        report["stages"]["paint_albedo"] = {"seconds": time.perf_counter() - t0,
                                            "texture": str(texture)}
    t0 = time.perf_counter()
    check = validate_file(paths.asset)
    report["stages"]["validate"] = {"seconds": time.perf_counter() - t0,
                                    "problems": [p.message for p in check.problems]}
    print(f"asset: {paths.asset} ({'valid' if not check.problems else 'INVALID'})")
    scene = author_shot(paths.asset, out / "scene.usda")
    t0 = time.perf_counter()
    renderer = Renderer(open_stage_guarded(scene), options, _eprint)
    try:
        doc = render_files(scene, out / "render", options, None, ocio, "Face",
                           progress=_eprint, renderer=renderer)
        report["stages"]["render"] = {"seconds": time.perf_counter() - t0,
                                      "tasks": doc["frames"][0]["tasks"],
                                      "render_json": str(out / "render" / "render.json")}
        _print_render(doc)
        if comparisons:
            t0 = time.perf_counter()
            report["comparisons"] = demo_comparisons(renderer, out / "render", ocio)
            report["stages"]["comparisons"] = {"seconds": time.perf_counter() - t0}
            for key in ("figure7", "regions_vs_one"):
                print(f"wrote {report['comparisons'][key]}")
    finally:
        renderer.close()
    report["valid"] = not check.problems
    report["total_seconds"] = time.perf_counter() - start
    return report


def cmd_run(args: argparse.Namespace) -> int:
    from ..errors import EXIT_CHECK_FAILED
    from ..fileio import atomic_write_json

    if not (args.captures / "capture.json").is_file():
        raise InputError("not a capture set (no capture.json)", args.captures)
    report = run_chain(args.captures, args.mesh, args.landmarks, args.output, args.k,
                       args.prepare_scan, args.paint_albedo, render_options(args),
                       ocio_source(args))
    atomic_write_json(args.output / "report.json", report)
    print(f"wrote {args.output / 'report.json'} ({report['total_seconds']:.1f} s)")
    return EXIT_OK if report["valid"] else EXIT_CHECK_FAILED


# ------------------------------------------------------------------------ demo extras


def side_by_side(left: Path, right: Path, out: Path, labels: tuple[str, str]) -> Path:
    """Two display PNGs next to each other over a grey backdrop, labelled if OIIO can
    find a font."""
    import numpy as np
    import OpenImageIO as oiio

    from ..imageio import write_ldr

    tiles = []
    for path, label in zip((left, right), labels, strict=True):
        buf = oiio.ImageBuf(str(path))
        px = np.asarray(buf.get_pixels(oiio.FLOAT), dtype=np.float32)
        if buf.has_error or px.ndim != 3 or px.shape[2] < 4:
            raise InputError(f"cannot read {path}: {buf.geterror()}", path)
        rgb, a = px[..., :3], px[..., 3:4]
        tile = oiio.ImageBuf(oiio.ImageSpec(px.shape[1], px.shape[0], 3, "float"))
        tile.set_pixels(oiio.ROI(), np.ascontiguousarray(rgb * a + 0.18 * (1 - a)))
        oiio.ImageBufAlgo.render_text(tile, 12, 28, label, 22, "", [1.0, 1.0, 1.0])
        tiles.append(np.asarray(tile.get_pixels(oiio.FLOAT)))
    return write_ldr(out, np.concatenate(tiles, axis=1), 8)


def demo_comparisons(renderer: Any, out: Path, ocio: str) -> dict[str, Any]:
    """The paper's figure 7 (texture-mapped only vs with scattering) and per-region vs one
    profile, rendered with ``renderer`` (which has rendered the scene with scattering and
    per-region profiles), so only diffusion and shading run again."""
    from ..render.renderer import write_outputs

    base = replace(renderer.options, aovs=("beauty",), scattering=True, single_profile=None)
    result: dict[str, Any] = {}
    pngs = {"scattering": out / "Face.png"}
    for label, opts in (("texture_only", {"scattering": False}),
                        ("one_profile", {"single_profile": "mean"})):
        renderer.options = replace(base, **opts)
        t0 = time.perf_counter()
        images, log = renderer.render()
        written = write_outputs(out, f"Face_{label}", images,
                                renderer.delegate.working_colorspace, ocio)
        pngs[label] = Path(written["png"])
        result[label] = {"seconds": time.perf_counter() - t0, "cached": log.cached,
                         "png": written["png"]}
    result["figure7"] = str(side_by_side(pngs["texture_only"], pngs["scattering"],
                                         out / "figure7_texture_vs_scattering.png",
                                         ("texture-mapped only", "with scattering")))
    result["regions_vs_one"] = str(side_by_side(pngs["scattering"], pngs["one_profile"],
                                                out / "per_region_vs_one_profile.png",
                                                ("six regional profiles", "one mean profile")))
    return result
