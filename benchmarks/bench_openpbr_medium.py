"""Benchmark: the OpenPBR medium of each region, path-traced, against the measured profile.

    python benchmarks/bench_openpbr_medium.py [-o benchmarks/results/openpbr_medium.json]

For the sample captures (through ``skinpipe ingest``; the level is the asset's default
albedo, as ``author`` makes it) and for the traced skin1 profile (tests/fixtures/physics,
its total reflectance as measured), the medium the asset's OpenPBR values imply (mean
free path = radius x scale, albedo from the colour by the specification's inversion) is
rendered by Mitsuba 3's ``volpath`` (one monochrome render a channel: an RGB medium fires
fireflies) as an index-matched slab under a normal distant light with a hard shadow edge,
seen from straight above: the image across the edge is the medium's edge-spread function
times its total reflectance over pi, and a render without the blocker gives that total.
The independent light tracer (tests/physics/light_tracer.py) traces the same medium
pencil-lit as a second peer. Printed per channel against the measured profile: the
edge-spread error (largest difference beyond the central two rings, share of the
plateau) and the total reflectance over the measured; the inversion's own model
residual beside them. Without the ``mitsuba`` package its columns are left out.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_mitsuba import mono_variant  # noqa: E402
from skinpipe.package_data import package_folder  # noqa: E402
from skinpipe.profile.edge import (  # noqa: E402
    edge_positions_mm,
    edge_width_mm,
    spread_beyond_rings,
)
from skinpipe.profile.io import read_profile_csv  # noqa: E402
from skinpipe.profile.medium import albedo_from_van_de_hulst, estimate_medium  # noqa: E402
from skinpipe.profile.models import ring_edges_mm  # noqa: E402
from skinpipe.usd.author import DEFAULT_ALBEDO  # noqa: E402
from tests.profile.test_medium import (  # noqa: E402
    traced_against_measured as traced_against,
)

PHOTONS = 200_000
MITSUBA_SPP = 1024
MITSUBA_PIXELS = (160, 96)
"""Columns across the edge, rows along it (averaged: the edge is the same all along)."""


def mitsuba_edge(variant: str, albedo: float, mfp_mm: float, g: float, half_width_mm: float,
                 blocked: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres x (mm) and the exit radiance across a hard shadow edge (light on
    x < 0) of an index-matched slab of the medium, under unit normal irradiance."""
    import mitsuba as mi

    mi.set_variant(variant)
    T = mi.ScalarTransform4f
    px, rows = MITSUBA_PIXELS
    depth = 200.0 * mfp_mm
    size = 400.0 * max(mfp_mm, half_width_mm)
    scene = {
        "type": "scene", "integrator": {"type": "volpath", "max_depth": -1},
        "sensor": {"type": "orthographic",
                   "to_world": T.look_at(origin=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0])
                   @ T.scale([half_width_mm, half_width_mm * rows / px, 1]),
                   "film": {"type": "hdrfilm", "width": px, "height": rows,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": MITSUBA_SPP}},
        "light": {"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0},
        "slab": {"type": "cube", "bsdf": {"type": "null"},
                 "to_world": T.translate([0, 0, -depth]) @ T.scale([size, size, depth]),
                 "interior": {"type": "homogeneous", "albedo": float(albedo),
                              "sigma_t": 1.0 / mfp_mm,
                              "phase": {"type": "hg", "g": g} if g else {"type": "isotropic"}}},
    }
    if blocked:  # a black card above the camera over x > 0: a straight, hard shadow
        scene["blocker"] = {"type": "rectangle", "bsdf": {"type": "diffuse",
                                                          "reflectance": 0.0},
                            "to_world": T.translate([size / 2, 0, 2.0])
                            @ T.scale([size / 2, size, 1])}
    image = np.array(mi.render(mi.load_dict(scene))).reshape(rows, px, -1)[..., 0]
    x = ((np.arange(px) + 0.5) / px * 2 - 1) * half_width_mm
    return x, image.mean(axis=0)


def mitsuba_against_measured(variant: str, radius: np.ndarray, values: np.ndarray,
                             reflectance: np.ndarray, colour: np.ndarray,
                             mfp_mm: np.ndarray, g: float) -> dict:
    """Edge error and total over measured of the medium (albedo from ``colour`` as a
    renderer following OpenPBR takes it), per channel."""
    outer = ring_edges_mm(radius)
    edge, total, noise = [], [], []
    albedo = albedo_from_van_de_hulst(colour, g)
    t = edge_positions_mm(radius)
    for c in range(3):
        measured = spread_beyond_rings(radius, values[:, c], t)
        width = float(edge_width_mm(t, measured)[0])
        half = float(np.clip(4.0 * width, 2.0, 0.9 * outer[-1]))
        x, lit = mitsuba_edge(variant, albedo[c], mfp_mm[c], g, half)
        _, full = mitsuba_edge(variant, albedo[c], mfp_mm[c], g, half, blocked=False)
        plateau = float(full.mean())
        # the measured edge averaged over each pixel's width, as the film's box does
        sub = x[:, None] + (np.arange(8)[None, :] + 0.5 - 4) / 8 * (x[1] - x[0])
        frac = spread_beyond_rings(radius, values[:, c], sub.reshape(-1)).reshape(-1)
        frac = (frac / measured[0]).reshape(sub.shape).mean(axis=1)
        keep = np.abs(x) >= outer[1]
        edge.append(round(float(np.abs(lit / plateau - frac)[keep].max()), 4))
        total.append(round(math.pi * plateau / float(reflectance[c]), 4))
        noise.append(round(float(full.std() / plateau), 4))
    return {"mitsuba_edge_error": edge, "mitsuba_over_measured_total": total,
            "mitsuba_pixel_noise": noise}


def traced_against_measured(name: str, radius: np.ndarray, values: np.ndarray,
                            reflectance: np.ndarray, variant: str | None) -> dict:
    start = time.perf_counter()
    medium = estimate_medium(radius, values, reflectance)
    seconds = time.perf_counter() - start
    edge, total = ([round(x, 4) for x in xs] for xs in traced_against(
        radius, values, reflectance, medium, PHOTONS, 40))
    row = {"profile": name, "model": medium.model, "anisotropy": medium.anisotropy,
           "single_scattering_albedo": medium.single_scattering_albedo.round(5).tolist(),
           "mean_free_path_mm": medium.mean_free_path_mm.round(4).tolist(),
           "subsurface_color": medium.subsurface_colour.round(4).tolist(),
           "model_edge_error": medium.edge_error.round(4).tolist(),
           "traced_edge_error": edge, "traced_over_measured_total": total,
           "inversion_seconds": round(seconds, 3)}
    print(f"{name:10s} {medium.model:7s} g {medium.anisotropy:.1f} model edge "
          f"{row['model_edge_error']}  traced edge {edge}  total traced/measured {total}",
          flush=True)
    if variant is not None:
        row.update(mitsuba_against_measured(variant, radius, values, reflectance,
                                            medium.subsurface_colour,
                                            medium.mean_free_path_mm, medium.anisotropy))
        print(f"{'':18s} Mitsuba volpath edge {row['mitsuba_edge_error']}  total "
              f"{row['mitsuba_over_measured_total']}  (pixel noise "
              f"{row['mitsuba_pixel_noise']})", flush=True)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "results" /
                                                      "openpbr_medium.json"))
    args = parser.parse_args()
    variant, why = mono_variant()
    print(f"Mitsuba: {variant or 'left out'} ({why})")
    rows = []
    fixtures = ROOT / "tests" / "fixtures" / "physics"
    data = np.loadtxt(fixtures / "skin1.csv", delimiter=",", skiprows=1)
    totals = json.loads((fixtures / "totals.json").read_text())["skin1"]["channels"]
    rows.append(traced_against_measured(
        "skin1", data[:, 0], data[:, 1:],
        np.array([math.pi * c["up_radiance_total"] for c in totals]), variant))
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "skinpipe", "ingest",
                        str(package_folder("samples", "captures")), "-o", f"{tmp}/p"],
                       check=True, stdout=subprocess.DEVNULL)
        for csv in sorted(Path(tmp, "p").glob("*.csv")):
            profile = read_profile_csv(csv)
            rows.append(traced_against_measured(csv.stem, profile.radius_mm, profile.values,
                                                np.array(DEFAULT_ALBEDO), variant))
    out = Path(args.output)
    out.write_text(json.dumps({"photons_per_channel": PHOTONS, "mitsuba_variant": variant,
                               "mitsuba_spp": MITSUBA_SPP, "mitsuba_pixels": MITSUBA_PIXELS,
                               "mitsuba_note": why, "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
