"""``skinpipe run``: ingest, fit, author, shot and render in one go."""

from __future__ import annotations

import argparse
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

from ..errors import EXIT_CHECK_FAILED, EXIT_OK, InputError
from .common import (
    _eprint,
    add_render_options,
    ocio_source,
    render_options,
)
from .render import _print_render


def add_parser(sub: argparse._SubParsersAction) -> None:
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
    from .author import author_from_args

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
    from ..fileio import atomic_write_json

    if not (args.captures / "capture.json").is_file():
        raise InputError("not a capture set (no capture.json)", args.captures)
    report = run_chain(args.captures, args.mesh, args.landmarks, args.output, args.k,
                       args.prepare_scan, args.paint_albedo, render_options(args),
                       ocio_source(args))
    atomic_write_json(args.output / "report.json", report)
    print(f"wrote {args.output / 'report.json'} ({report['total_seconds']:.1f} s)")
    return EXIT_OK if report["valid"] else EXIT_CHECK_FAILED


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
