"""Benchmark: the OpenPBR medium of each region, path-traced, against the measured profile.

    python benchmarks/bench_openpbr_medium.py [--spp N] [--profiles NAME ...]
                                              [-o benchmarks/results/openpbr_medium.json]

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
plateau; Mitsuba's columns averaged in bins, BINS, with the bins' noise beside, from
the spread of its rows) and the total reflectance over the measured; the inversion's
own model residual beside them; and Mitsuba's edge against the light tracer's of the
same medium: chi^2 a bin with Mitsuba's noise (about 1 where the two agree), and
their largest difference.
Without the ``mitsuba`` package its columns are left out.

Mitsuba's paths run without Russian roulette, cut at the depth where the albedo's
power falls below 1e-4: its roulette survives at most 0.95 a bounce and divides by it,
so where the single-scattering albedo exceeds 0.95 (skin's, forward scattering) a
long path's weight grows at every bounce (alpha / 0.95) and fires fireflies (a red
channel of albedo 0.99 had 11% column noise at 256 samples, 1% without roulette).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from functools import cached_property
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
REACH_MM = 60.0
"""How far the tracer tallies for the comparison with Mitsuba (the measured edge stops
at the capture's radius; at g 0.9 red leaves 5-11% of its light beyond 6.3 mm)."""
MITSUBA_SPP = 1024
"""Samples a pixel by default (--spp)."""
DEPTH_CUT = 1e-4
"""A path stops where the albedo's power (its weight) falls below this: the bias."""
COLUMNS, ROWS = 160, 96
"""Columns across the narrowest window a render serves, rows along the edge (averaged:
the edge is the same all along)."""
BINS = 20
"""Bins a side of the edge (beyond the central two rings) in which Mitsuba's columns and
the measured edge are averaged alike before their largest difference is taken: a
column's noise would otherwise pass for edge error (the edge moves over about eight
bins, so binning leaves its shape)."""
GROUP_SPREAD = 2.0
"""Edges of one medium whose windows (in mean free paths) differ by at most this factor
share one render: the image is the same at any length scale (mu_t = 1 here, x read
in mean free paths), so the six sample regions, one albedo a channel, need few."""


def mitsuba_edge(variant: str, albedo: float, g: float, half_width_mfp: float,
                 columns: int, spp: int, blocked: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Column centres x (mean free paths), the exit radiance across a hard shadow edge
    (light on x < 0) of an index-matched slab of the medium (mu_t = 1) under unit normal
    irradiance, and its standard error."""
    import mitsuba as mi

    mi.set_variant(variant)
    T = mi.ScalarTransform4f
    half = half_width_mfp
    depth, size = 200.0, 400.0 * max(1.0, half)
    scene = {
        "type": "scene",
        "integrator": {"type": "volpath", "rr_depth": 1 << 30,
                       "max_depth": max(2, math.ceil(math.log(DEPTH_CUT) / math.log(albedo)))},
        "sensor": {"type": "orthographic",
                   "to_world": T.look_at(origin=[0, 0, 1], target=[0, 0, 0], up=[0, 1, 0])
                   @ T.scale([half, half * ROWS / columns, 1]),
                   "film": {"type": "hdrfilm", "width": columns, "height": ROWS,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}},
        "light": {"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0},
        "slab": {"type": "cube", "bsdf": {"type": "null"},
                 "to_world": T.translate([0, 0, -depth]) @ T.scale([size, size, depth]),
                 "interior": {"type": "homogeneous", "albedo": float(albedo), "sigma_t": 1.0,
                              "phase": {"type": "hg", "g": g} if g else {"type": "isotropic"}}},
    }
    if blocked:  # a black card above the camera over x > 0: a straight, hard shadow
        scene["blocker"] = {"type": "rectangle", "bsdf": {"type": "diffuse",
                                                          "reflectance": 0.0},
                            "to_world": T.translate([size / 2, 0, 2.0])
                            @ T.scale([size / 2, size, 1])}
    image = np.array(mi.render(mi.load_dict(scene))).reshape(ROWS, columns, -1)[..., 0]
    x = ((np.arange(columns) + 0.5) / columns * 2 - 1) * half
    # the rows are independent estimates of one edge: their spread is the mean's noise
    return x, image.mean(axis=0), image.std(axis=0, ddof=1) / math.sqrt(ROWS)


@dataclass
class EdgeJob:
    """One channel of one profile: its measured edge and the medium a renderer derives
    from the exported OpenPBR values (albedo from the colour, as the specification's
    inversion gives it)."""

    row: dict
    channel: int
    radius: np.ndarray
    values: np.ndarray
    reflectance: float
    albedo: float
    mfp_mm: float
    g: float
    traced_radius: np.ndarray
    traced: np.ndarray
    """The light tracer's radiance of the same medium at traced_radius: the measured
    rings continued to REACH_MM, since Mitsuba's edge holds all the light."""

    @cached_property
    def half_mm(self) -> float:
        """Four edge widths either side, within the measured radii."""
        t = edge_positions_mm(self.radius)
        measured = spread_beyond_rings(self.radius, self.values, t)
        outer = ring_edges_mm(self.radius)
        return float(np.clip(4.0 * edge_width_mm(t, measured)[0], 2.0, 0.9 * outer[-1]))


def _bins(x_mm: np.ndarray, inner_mm: float, half_mm: float) -> list[np.ndarray]:
    """BINS groups of columns a side of the edge, within inner_mm <= |x| <= half_mm."""
    out = []
    for side in (x_mm < 0, x_mm > 0):
        keep = np.flatnonzero(side & (np.abs(x_mm) >= inner_mm) & (np.abs(x_mm) <= half_mm))
        out += np.array_split(keep, min(BINS, keep.size))
    return out


def _edge_of(radius: np.ndarray, values: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A profile's edge-spread function over its total, averaged over each column's
    width as the film's box does."""
    first = spread_beyond_rings(radius, values, edge_positions_mm(radius))[0]
    sub = x[:, None] + (np.arange(8)[None, :] + 0.5 - 4) / 8 * (x[1] - x[0])
    return (spread_beyond_rings(radius, values, sub.reshape(-1)).reshape(sub.shape)
            / first).mean(axis=1)


def _compare(job: EdgeJob, x_mfp: np.ndarray, lit: np.ndarray, error: np.ndarray,
             plateau: float) -> None:
    """Into ``job``'s row: Mitsuba's edge error against the measured profile, its total,
    its bins' noise, and its agreement with the light tracer's edge of the same medium
    (chi^2 per bin with Mitsuba's noise, and the largest difference)."""
    x = x_mfp * job.mfp_mm
    bins = _bins(x, float(ring_edges_mm(job.radius)[1]), job.half_mm)
    mitsuba = np.array([lit[b].mean() for b in bins]) / plateau
    noise = np.array([math.sqrt(float(np.sum(error[b] ** 2))) / b.size for b in bins]) / plateau
    measured = _edge_of(job.radius, job.values, x)
    traced = _edge_of(job.traced_radius, job.traced, x)
    measured, traced = (np.array([v[b].mean() for b in bins]) for v in (measured, traced))
    c = job.channel
    for key, value in (("mitsuba_edge_error", np.abs(mitsuba - measured).max()),
                       ("mitsuba_over_measured_total", math.pi * plateau / job.reflectance),
                       ("mitsuba_bin_noise", noise.mean()),
                       ("mitsuba_vs_traced_chi2_per_bin",
                        np.mean(((mitsuba - traced) / noise) ** 2)),
                       ("mitsuba_vs_traced_largest", np.abs(mitsuba - traced).max())):
        job.row.setdefault(key, [0.0] * 3)[c] = round(float(value), 4)


def mitsuba_columns(variant: str, jobs: list[EdgeJob], spp: int) -> int:
    """Render every job's medium across a shadow edge, sharing renders between jobs of one
    medium (see GROUP_SPREAD), and fill the rows' Mitsuba columns. Returns the renders."""
    renders = 0
    media: dict[tuple[float, float], list[EdgeJob]] = {}
    for job in jobs:
        media.setdefault((round(job.albedo, 9), job.g), []).append(job)
    for (albedo, g), members in media.items():
        members.sort(key=lambda j: j.half_mm / j.mfp_mm)
        while members:
            narrowest = members[0].half_mm / members[0].mfp_mm
            group = [j for j in members if j.half_mm / j.mfp_mm <= GROUP_SPREAD * narrowest]
            members = members[len(group):]
            half = group[-1].half_mm / group[-1].mfp_mm
            columns = math.ceil(COLUMNS * half / narrowest)
            start = time.perf_counter()
            x, lit, error = mitsuba_edge(variant, albedo, g, half, columns, spp)
            quarter = max(16, spp // 4)  # the plateau is the mean of a whole image
            _, full, _ = mitsuba_edge(variant, albedo, g, half, columns, quarter,
                                      blocked=False)
            renders += 2
            for job in group:
                _compare(job, x, lit, error, float(full.mean()))
            print(f"  Mitsuba: albedo {albedo:.5f} g {g}, {len(group)} edge(s), {columns} "
                  f"columns, {time.perf_counter() - start:.0f} s", flush=True)
    return renders


def traced_against_measured(name: str, radius: np.ndarray, values: np.ndarray,
                            reflectance: np.ndarray) -> tuple[dict, list[EdgeJob]]:
    """The inversion and the light tracer's columns of one profile, and its Mitsuba jobs."""
    start = time.perf_counter()
    medium = estimate_medium(radius, values, reflectance)
    seconds = time.perf_counter() - start
    edge, total, traced_radius, traced = traced_against(radius, values, reflectance, medium,
                                                        PHOTONS, 40, REACH_MM)
    edge, total = [round(x, 4) for x in edge], [round(x, 4) for x in total]
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
    albedo = albedo_from_van_de_hulst(medium.subsurface_colour, medium.anisotropy)
    jobs = [EdgeJob(row, c, radius, values[:, c], float(reflectance[c]), float(albedo[c]),
                    float(medium.mean_free_path_mm[c]), medium.anisotropy, traced_radius,
                    traced[:, c])
            for c in range(3)]
    return row, jobs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "results" /
                                                      "openpbr_medium.json"))
    parser.add_argument("--spp", type=int, default=MITSUBA_SPP,
                        help=f"Mitsuba's samples a pixel (default {MITSUBA_SPP})")
    parser.add_argument("--profiles", nargs="+", default=None, metavar="NAME",
                        help="only these (skin1 and the sample regions: forehead, lips, "
                             "chin, cheekbone, cheek, nose)")
    args = parser.parse_args()
    wanted = set(args.profiles) if args.profiles else None
    variant, why = mono_variant()
    print(f"Mitsuba: {variant or 'left out'} ({why})")
    rows, jobs = [], []

    def add(name: str, radius: np.ndarray, values: np.ndarray, reflectance: np.ndarray
            ) -> None:
        if wanted is None or name in wanted:
            row, its_jobs = traced_against_measured(name, radius, values, reflectance)
            rows.append(row)
            jobs.extend(its_jobs)

    fixtures = ROOT / "tests" / "fixtures" / "physics"
    data = np.loadtxt(fixtures / "skin1.csv", delimiter=",", skiprows=1)
    totals = json.loads((fixtures / "totals.json").read_text())["skin1"]["channels"]
    add("skin1", data[:, 0], data[:, 1:],
        np.array([math.pi * c["up_radiance_total"] for c in totals]))
    with tempfile.TemporaryDirectory() as tmp:
        subprocess.run([sys.executable, "-m", "skinpipe", "ingest",
                        str(package_folder("samples", "captures")), "-o", f"{tmp}/p"],
                       check=True, stdout=subprocess.DEVNULL)
        for csv in sorted(Path(tmp, "p").glob("*.csv")):
            profile = read_profile_csv(csv)
            add(csv.stem, profile.radius_mm, profile.values, np.array(DEFAULT_ALBEDO))
    renders = 0
    if variant is not None:
        start = time.perf_counter()
        renders = mitsuba_columns(variant, jobs, args.spp)
        print(f"Mitsuba volpath, {args.spp} samples a pixel, {renders} renders in "
              f"{time.perf_counter() - start:.0f} s: edge, total over measured (bin noise)")
        for row in rows:
            print(f"{row['profile']:10s} {row['mitsuba_edge_error']}  "
                  f"{row['mitsuba_over_measured_total']}  ({row['mitsuba_bin_noise']}); "
                  f"against the tracer: chi2 a bin {row['mitsuba_vs_traced_chi2_per_bin']}, "
                  f"largest {row['mitsuba_vs_traced_largest']}")
    out = Path(args.output)
    out.write_text(json.dumps({"photons_per_channel": PHOTONS, "mitsuba_variant": variant,
                               "mitsuba_spp": args.spp, "mitsuba_depth_cut": DEPTH_CUT,
                               "mitsuba_rows": ROWS, "mitsuba_bins_a_side": BINS,
                               "mitsuba_renders": renders, "mitsuba_note": why,
                               "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
