"""Benchmark: direct light on the demo face, skinpipe against Mitsuba 3 at equal error.

Each renderer is measured against its own converged reference of the same scene (the
demo's shot with scattering off and the seal deactivated in both; skinpipe: 256 light
samples, every texel tracing all of them; Mitsuba: ``direct`` integrator, white
Lambertian, low-discrepancy samples, one light and one cosine-weighted direction each
with multiple importance sampling, 512 samples per pixel), as the relative RMS error
of the irradiance over the face's pixels. skinpipe runs at its defaults (16 light
samples, interleaved); Mitsuba's samples per pixel are swept, and since its error
falls as 1/sqrt(spp) and its time grows linearly, the time it needs for skinpipe's
error follows from the sweep. Prints the ratio skinpipe / Mitsuba (at equal error;
< 1: skinpipe faster) and writes JSON. Mitsuba's LLVM variant is used where it runs (a
probe in a child process: on LLVM 14/15 it aborts), its scalar one otherwise; the
JSON says which. Without the ``mitsuba`` package the Mitsuba column is skipped, with
the reason.

    python benchmarks/bench_mitsuba.py [--scene DEMO/scene.usda] [--resolution 384]
                                       [-o benchmarks/results/mitsuba.json]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from skinpipe.render.options import RenderOptions
from skinpipe.render.renderer import Renderer
from skinpipe.render.surface.unwrap import triangulate
from skinpipe.usd.io import open_stage_guarded

LLVM_PROBE = """
import mitsuba as mi
mi.set_variant("llvm_ad_rgb")
s = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
    "sensor": {"type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
    "b": {"type": "sphere", "center": [0, 0, -5]},
    "e": {"type": "constant"}})
mi.render(s, spp=1)
print("ok")
"""


def mitsuba_variant() -> tuple[str | None, str]:
    """The Mitsuba variant to use and why: LLVM if a probe render in a child works."""
    try:
        import mitsuba  # noqa: F401
    except ImportError as exc:
        return None, f"mitsuba is not installed ({exc}): pip install mitsuba"
    probe = subprocess.run([sys.executable, "-c", LLVM_PROBE], capture_output=True,
                           text=True, timeout=300)
    if probe.returncode == 0 and "ok" in probe.stdout:
        return "llvm_ad_rgb", "the LLVM variant runs here"
    why = (probe.stderr.strip().splitlines() or ["no output"])[0][:160]
    return "scalar_rgb", f"the LLVM variant does not run here ({why}); scalar instead"


def mono_variant() -> tuple[str | None, str]:
    """:func:`mitsuba_variant` in its monochrome form: one render a channel, for media
    (an RGB medium fires fireflies where one channel is far thinner than another)."""
    variant, why = mitsuba_variant()
    return (None if variant is None else variant.replace("_rgb", "_mono")), why


def seal_free_scene(scene: Path, out: Path) -> Path:
    """A layer over ``scene`` that deactivates meshes hidden from the camera (the seal):
    Mitsuba has no such visibility, so neither renderer gets them."""
    from pxr import Sdf, Usd, UsdGeom

    stage = open_stage_guarded(scene)
    hidden = [p.GetPath() for p in stage.Traverse() if p.IsA(UsdGeom.Mesh) and
              p.GetName() == "Seal"]
    layer = Sdf.Layer.CreateNew(str(out))
    layer.subLayerPaths = [str(scene.resolve())]
    over = Usd.Stage.Open(layer)
    for path in hidden:
        over.OverridePrim(path).SetActive(False)
    layer.Save()
    return out


def rel_rmse(image: np.ndarray, reference: np.ndarray, mask: np.ndarray) -> float:
    a, b = image[mask].mean(axis=-1), reference[mask].mean(axis=-1)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.mean(b))


def skinpipe_irradiance(scene: Path, resolution: int, **opts: Any
                        ) -> tuple[np.ndarray, np.ndarray, float]:
    """The irradiance AOV, the alpha, and the render's seconds (a fresh renderer: the
    texture-space work is not cached; OpenCL programs are, as for any warm run)."""
    options = RenderOptions(resolution=(resolution, resolution), scattering=False,
                            aovs=("beauty", "irradiance"), **opts)
    start = time.perf_counter()
    renderer = Renderer(open_stage_guarded(scene), options)
    try:
        images, _ = renderer.render()
    finally:
        renderer.close()
    return images["irradiance"], images["beauty"][..., 3], time.perf_counter() - start


def _write_ply(path: Path, points: np.ndarray, tris: np.ndarray) -> None:
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {len(tris)}\nproperty list uchar int vertex_indices\n"
              "end_header\n").encode()
    faces = np.empty(len(tris), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"], faces["i"] = 3, tris
    path.write_bytes(header + points.astype("<f4").tobytes() + faces.tobytes())


def mitsuba_scene(scene: Path, resolution: int, folder: Path, variant: str
                  ) -> dict[str, Any]:
    """The scene as skinpipe's delegate reads it, as a Mitsuba scene dictionary."""
    import mitsuba as mi

    mi.set_variant(variant)
    stage = open_stage_guarded(scene)
    renderer = Renderer(stage, RenderOptions(resolution=(resolution, resolution)))
    data = renderer.delegate.sync(None)
    renderer.close()
    cam = data.camera
    back, up = cam.rotation[:, 2], cam.rotation[:, 1]
    fov = math.degrees(2 * math.atan(0.5 * cam.horizontal_aperture / cam.focal_length))
    doc: dict[str, Any] = {
        "type": "scene",
        # MIS of one light and one cosine sample a pixel sample (the dome is sampled
        # best through the BSDF, the small key through the light), low-discrepancy
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 1,
                       "hide_emitters": True},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f().look_at(
                       origin=cam.position.tolist(), target=(cam.position - back).tolist(),
                       up=up.tolist()),
                   "sampler": {"type": "ldsampler", "sample_count": 16},
                   "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                            "rfilter": {"type": "box"}, "pixel_format": "rgb"}},
    }
    for i, mesh in enumerate(m for m in data.meshes if m.camera_visible):
        ply = folder / f"mesh{i}.ply"
        _write_ply(ply, mesh.mesh.points, triangulate(mesh.mesh))
        doc[f"mesh{i}"] = {"type": "ply", "filename": str(ply),
                           "bsdf": {"type": "twosided", "bsdf": {
                               "type": "diffuse",
                               "reflectance": {"type": "rgb", "value": 1.0}}}}
    for i, light in enumerate(data.lights):
        radiance = {"type": "rgb", "value": [float(x) for x in light.radiance]}
        if light.kind == "sphere":
            doc[f"light{i}"] = {"type": "sphere", "center": light.position.tolist(),
                                "radius": float(light.radius),
                                "emitter": {"type": "area", "radiance": radiance}}
        elif light.kind == "dome":
            doc[f"light{i}"] = {"type": "constant", "radiance": radiance}
        else:
            raise SystemExit(f"bench_mitsuba: light kind {light.kind} not mapped")
    return doc


def mitsuba_sweep(doc: dict[str, Any], variant: str, spps: list[int], reference_spp: int
                  ) -> dict[str, Any]:
    import mitsuba as mi

    mi.set_variant(variant)
    scene = mi.load_dict(doc)
    mi.render(scene, spp=1)  # JIT and scene set-up out of the timings
    start = time.perf_counter()
    reference = np.array(mi.render(scene, spp=reference_spp)) * math.pi  # white: E / pi
    ref_s = time.perf_counter() - start
    rows = []
    for spp in spps:
        start = time.perf_counter()
        img = np.array(mi.render(scene, spp=spp, seed=spp)) * math.pi
        rows.append({"spp": spp, "seconds": time.perf_counter() - start, "image": img})
    return {"reference": reference, "reference_seconds": ref_s, "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path, default=None,
                        help="a demo's scene.usda (default: run skinpipe demo first)")
    parser.add_argument("--resolution", type=int, default=384)
    parser.add_argument("-o", "--output", type=Path,
                        default=Path("benchmarks/results/mitsuba.json"))
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="skinpipe-mitsuba-") as tmp:
        folder = Path(tmp)
        scene = args.scene
        if scene is None:
            subprocess.run([sys.executable, "-m", "skinpipe", "demo", "-o",
                            str(folder / "demo")], check=True)
            scene = folder / "demo" / "scene.usda"
        bench = seal_free_scene(scene, folder / "bench_scene.usda")
        res = args.resolution
        skinpipe_irradiance(bench, res)  # programs built, caches warm
        ref, alpha, ref_s = skinpipe_irradiance(bench, res, light_samples=256,
                                                shadow_sampling="full")
        img, _, seconds = skinpipe_irradiance(bench, res)
        mask = alpha >= 1.0
        ours = {"light_samples": 16, "shadow_sampling": "interleaved",
                "light_sequence": RenderOptions().light_sequence, "seconds": seconds,
                "rel_rmse": rel_rmse(img, ref, mask), "reference_seconds": ref_s}
        result: dict[str, Any] = {"machine": {"platform": platform.platform(),
                                              "cores": os.cpu_count()},
                                  "resolution": res, "face_pixels": int(mask.sum()),
                                  "skinpipe": ours}
        variant, why = mitsuba_variant()
        result["mitsuba_variant"], result["mitsuba_note"] = variant, why
        if variant is not None:
            sweep = mitsuba_sweep(mitsuba_scene(bench, res, folder, variant), variant,
                                  [4, 16, 64], 512)  # ldsampler: powers of 4
            rows = []
            for row in sweep["rows"]:
                err = rel_rmse(row["image"], sweep["reference"], mask)
                rows.append({"spp": row["spp"], "seconds": row["seconds"], "rel_rmse": err})
            # error ~ 1/sqrt(spp), time ~ spp: from the largest sweep point
            last = rows[-1]
            spp_equal = last["spp"] * (last["rel_rmse"] / ours["rel_rmse"]) ** 2
            mitsuba_s = last["seconds"] * spp_equal / last["spp"]
            mask_agree = float(np.mean((sweep["reference"].mean(-1) > 0) == mask))
            result["mitsuba"] = {"rows": rows, "spp_at_equal_error": spp_equal,
                                 "seconds_at_equal_error": mitsuba_s,
                                 "reference_spp": 512,
                                 "reference_seconds": sweep["reference_seconds"],
                                 "coverage_agreement": mask_agree}
            result["ratio_skinpipe_over_mitsuba"] = seconds / mitsuba_s
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=2) + "\n")
    print(f"skinpipe: {ours['seconds']:.2f} s at relative RMS error {ours['rel_rmse']:.4f} "
          f"(16 light samples, interleaved; {mask.sum()} face pixels at {res}x{res})")
    if "mitsuba" in result:
        m = result["mitsuba"]
        for row in m["rows"]:
            print(f"mitsuba {variant}: {row['spp']:>3} spp {row['seconds']:.2f} s, error "
                  f"{row['rel_rmse']:.4f}")
        print(f"mitsuba at skinpipe's error: {m['spp_at_equal_error']:.1f} spp, "
              f"{m['seconds_at_equal_error']:.2f} s; skinpipe / mitsuba = "
              f"{result['ratio_skinpipe_over_mitsuba']:.2f} (pixel coverage agreement "
              f"{m['coverage_agreement']:.3f})")
    else:
        print(f"mitsuba: skipped: {why}")
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
