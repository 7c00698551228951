"""Benchmark: the face's texture-space diffusion (naive, gather, ours) and its irradiance.

    python benchmarks/bench_render.py SCENE.usda [--sizes 1024,2048] [--naive-sizes 1024]
                                      [-o benchmarks/results/render.json]

SCENE is a rendered-ready stage such as demo_out/scene.usda (`skinpipe demo`). For
each texture size the same irradiance (after the albedo split) is diffused by:

- naive: every region's own profile (its own variances), each term blurred from the
  irradiance by the gather kernel, weighted by the region's weight map, summed;
- gather: the renderer's first diffusion (shared 12-variance grid, incremental gather
  blurs, `--blur gather`);
- ours: the recursive Gaussian on a pyramid (`skinpipe.render.diffusion.diffuse_prepared`) on
  the shared 12- and 6-variance grids and on each region's own variances, with the
  texture layout prepared once (`DiffusionLayout`: what a renderer keeps for every
  frame and light; its build is timed on its own, and `ours grid 6, layout included`
  is `diffuse` building it in the call).

Reported: seconds (best of --repeats), full-resolution blur equivalents, and the
largest difference to `naive` over covered texels relative to its peak. Irradiance:
shadow rays and Mrays/s of the same texture-space irradiance task.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np


def best_of(fn: Callable[[], Any], repeats: int) -> tuple[float, Any]:
    best, out = float("inf"), None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def naive_diffusion(pre: np.ndarray, maps: Any, fits: Any) -> np.ndarray:
    """Each region's own terms, each a gather blur of the irradiance, region-weighted."""
    from skinpipe.render.diffusion.gather import diffuse_gather

    out = np.zeros_like(pre)
    for r, fit in enumerate(fits):
        rw = maps.region_weights[..., r]
        if not rw.any():
            continue
        w = fit.weights / fit.weights.sum(axis=0, keepdims=True)
        for v, wk in zip(fit.variances_mm2, w, strict=True):
            blurred, _ = diffuse_gather(pre, maps.mm_per_texel_u, maps.mm_per_texel_v,
                                        maps.coverage, np.array([v]), np.ones((1, 3)))
            out += rw[..., None] * wk * blurred
    return out


def bench_size(stage: Any, size: int, with_naive: bool, repeats: int) -> dict[str, Any]:
    """Texture maps and irradiance at ``size``, then every diffusion timed on them."""
    from skinpipe.render.diffusion.diffuse import diffuse, diffuse_prepared
    from skinpipe.render.diffusion.gather import diffuse_gather
    from skinpipe.render.diffusion.layout import DiffusionLayout
    from skinpipe.render.diffusion.terms import diffusion_terms
    from skinpipe.render.frame import TaskLog
    from skinpipe.render.light.raytrace import RayScene
    from skinpipe.render.options import RenderOptions
    from skinpipe.render.renderer import Renderer
    from skinpipe.render.surface.unwrap import triangulate

    # no image (8 x 8 pixels): interleaving period 2 at every size, the texture-space
    # work per texel the same
    renderer = Renderer(stage, RenderOptions(texture_size=size, resolution=(8, 8),
                                             interleave_period=2))
    try:
        sc = renderer.delegate.sync()
        mesh = sc.skin[0]
        log = TaskLog()
        rays = RayScene([(m.mesh.points, triangulate(m.mesh)) for m in sc.meshes])
        tex = renderer.skin_textures(log, sc, mesh)
        renderer.irradiance(log, sc, tex, rays, {})
        renderer.albedo(log, sc, tex)
    finally:
        renderer.close()
    maps = tex.maps
    covered = maps.coverage > 0
    pre = tex.irradiance * np.power(tex.albedo_map(), 0.5)
    texel_mm = float(np.median(np.sqrt(maps.mm_per_texel_u * maps.mm_per_texel_v)[covered]))
    irr = log.measures["irradiance"]
    row: dict[str, Any] = {"texture_size": size, "covered_texels": int(covered.sum()),
                           "mm_per_texel": texel_mm, "regions": len(mesh.fits),
                           "irradiance_rays": irr["rays"], "irradiance_s": irr["seconds"],
                           "irradiance_mrays_per_s": irr["mrays_per_s"], "diffusion": {}}
    print(f"texture {size}: {covered.sum()} covered texels, {texel_mm:.3f} mm/texel; "
          f"irradiance {irr['rays'] / 1e6:.1f} M rays, {irr['mrays_per_s']:.2f} Mrays/s",
          flush=True)

    def run(name: str, fn: Callable[[], Any], repeats: int) -> Any:
        fn()  # warm-up: kernels compile on first use
        seconds, result = best_of(fn, repeats)
        out, stats = result if isinstance(result, tuple) else (result, None)
        entry = {"seconds": seconds}
        if stats is not None:
            entry |= {"blur_passes": stats.passes,
                      "full_resolution_blurs": stats.full_blurs}
        row["diffusion"][name] = entry
        print(f"  {name:<22} {seconds:8.2f} s", flush=True)
        return out

    def layout() -> DiffusionLayout:
        return DiffusionLayout(renderer.device, maps.mm_per_texel_u, maps.mm_per_texel_v,
                               maps.coverage, maps.region_weights)

    layout()  # warm-up: kernels compile on first use
    row["diffusion_layout_s"], prepared = best_of(layout, repeats)
    print(f"  {'layout (once per UV layout)':<22} {row['diffusion_layout_s']:8.2f} s", flush=True)

    def ours(terms: Any) -> Any:
        return diffuse_prepared(prepared, pre, terms.variances_mm2, terms.weights)

    floor = (0.5 * texel_mm) ** 2
    grids = {g: diffusion_terms(mesh.fits, g, None, floor_mm2=floor) for g in (12, 6)}
    outs = {f"ours grid {g}": run(f"ours grid {g}", partial(ours, t), repeats)
            for g, t in grids.items()}
    run("ours grid 6, layout included", lambda: diffuse(
        pre, maps.mm_per_texel_u, maps.mm_per_texel_v, maps.coverage, grids[6].variances_mm2,
        grids[6].weights, maps.region_weights), repeats)
    own = diffusion_terms(mesh.fits, 0, None, floor_mm2=floor)
    outs["ours own variances"] = run("ours own variances", partial(ours, own), repeats)
    if not with_naive:
        return row
    outs["gather grid 12"] = run("gather grid 12", lambda: diffuse_gather(
        pre, maps.mm_per_texel_u, maps.mm_per_texel_v, maps.coverage,
        grids[12].variances_mm2, grids[12].weights, maps.region_weights), 1)
    naive = run("naive per region/term", lambda: naive_diffusion(pre, maps, mesh.fits), 1)
    peak = float(np.abs(naive[covered]).max())
    naive_s = row["diffusion"]["naive per region/term"]["seconds"]
    for name, out in outs.items():
        diff = np.abs(np.asarray(out)[covered] - naive[covered]).max(axis=1) / peak
        entry = row["diffusion"][name]
        entry |= {"max_diff_vs_naive": float(diff.max()),
                  "p99_diff_vs_naive": float(np.percentile(diff, 99)),
                  "speedup_vs_naive": naive_s / entry["seconds"]}
        print(f"  {name:<22} vs naive: max {diff.max():.2e}, p99 "
              f"{np.percentile(diff, 99):.2e} of the peak, "
              f"{entry['speedup_vs_naive']:.1f}x faster", flush=True)
    return row


def main() -> None:
    from skinpipe.usd.io import open_stage_guarded

    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", type=Path)
    ap.add_argument("--sizes", default="1024,2048")
    ap.add_argument("--naive-sizes", default="1024",
                    help="sizes at which the naive and gather diffusions also run (they take "
                         "minutes at 2048)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("-o", "--output", type=Path, default=Path("benchmarks/results/render.json"))
    args = ap.parse_args()
    naive_sizes = {int(s) for s in args.naive_sizes.split(",") if s}
    stage = open_stage_guarded(args.scene)
    rows = [bench_size(stage, size, size in naive_sizes, args.repeats)
            for size in (int(s) for s in args.sizes.split(","))]
    doc = {"benchmark": "render", "scene": str(args.scene), "machine": platform.platform(),
           "rows": rows}
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(doc, indent=2) + "\n")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
