"""Benchmark: curved skin against a path tracer, through the CLI.

    python benchmarks/bench_curved.py [-o benchmarks/results/curved.json]

A sphere of skin1 (Jensen et al. 2001, index-matched) of radius 10 mm and 5 mm under a
distant light at 0 and 60 degrees, seen from straight above. Mitsuba 3's ``volpath``
renders the medium itself (one monochrome render a channel, 4096 samples a pixel, a strip
through the centre); skinpipe renders skin1's traced profile the user's way (the CSV
through ``fit`` at its defaults, the sphere without UVs through ``author``, ``render
--ior 1 --rho-s 0`` with the albedo skin1 measures) and, its peer, the same with
``--no-transmission`` (no first scatter, no thin parts). Printed per channel along the
strip: the centre's radiance over the truth's, the 50%, 10% and 2% points of the centre's
level on the terminator's side less the truth's (mm), the light just past the geometric
terminator (1 to 2 mm beyond it) over the truth's, and the largest seam step of the
render (tests/render/diffusion/test_curved_seams.py's measure). Without the ``mitsuba``
package, and lit from straight above (the terminator is the rim), only the seam steps.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_mitsuba import mono_variant  # noqa: E402
from tests.render.diffusion.test_curved_seams import _worst_step  # noqa: E402
from tests.render.terminator import (  # noqa: E402
    sphere_render,
    terminator_figures,
)

SKIN1 = ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48])
SPP = 4096
STRIP = (480, 4)
CASES = ((10.0, 0.0), (10.0, 60.0), (5.0, 0.0), (5.0, 60.0))


def mitsuba_strip(variant: str, radius_mm: float, angle_deg: float, spp: int = SPP
                  ) -> np.ndarray:
    """(3, STRIP[0]) the path-traced radiance along the strip through the centre."""
    import mitsuba as mi

    mi.set_variant(variant)
    T = mi.ScalarTransform4f
    half = 1.2 * radius_mm
    px, rows = STRIP
    light = [math.sin(math.radians(angle_deg)), 0.0, math.cos(math.radians(angle_deg))]
    out = []
    for s, a in zip(*SKIN1, strict=True):
        scene = {
            "type": "scene", "integrator": {"type": "volpath", "max_depth": -1},
            "sensor": {"type": "orthographic",
                       "to_world": T.look_at(origin=[0, 0, 5 * radius_mm], target=[0, 0, 0],
                                             up=[0, 1, 0]) @ T.scale([half, half * rows / px, 1]),
                       "film": {"type": "hdrfilm", "width": px, "height": rows,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": spp}},
            "light": {"type": "directional", "direction": [-x for x in light],
                      "irradiance": 1.0},
            "ball": {"type": "sphere", "radius": radius_mm, "bsdf": {"type": "null"},
                     "interior": {"type": "homogeneous", "albedo": s / (s + a),
                                  "sigma_t": s + a, "phase": {"type": "isotropic"}}}}
        image = np.array(mi.render(mi.load_dict(scene))).reshape(rows, px, -1)[..., 0]
        out.append(image.mean(axis=0))
    return np.array(out)


def strip_figures(rgb: np.ndarray, truth: np.ndarray, radius: float, angle: float
                  ) -> dict[str, dict[str, dict[str, float]]]:
    """Per channel :func:`terminator_figures` of the render's strip and the truth's."""
    width = 2.4 * radius
    x_t = ((np.arange(STRIP[0]) + 0.5) / STRIP[0] * 2 - 1) * 1.2 * radius
    h = rgb.shape[0]
    x_s = (np.arange(rgb.shape[1]) + 0.5) / rgb.shape[1] * width - width / 2
    strip = rgb[h // 2 - 2:h // 2 + 2].mean(axis=0)
    terminator = -radius * math.cos(math.radians(angle))
    return {name: {"truth": terminator_figures(x_t, truth[c], terminator),
                   "skinpipe": terminator_figures(x_s, strip[:, c], terminator)}
            for c, name in enumerate("RGB")}


def figures_line(figures: dict[str, dict[str, dict[str, float]]]) -> str:
    """The figures of :func:`strip_figures` against the truth, a line a channel."""
    line = ""
    for name, f in figures.items():
        t, s = f["truth"], f["skinpipe"]
        line += (f"\n  {name}: centre {s['centre'] / t['centre']:.3f} of the truth; "
                 f"50/10/2% points {s['point_50_mm'] - t['point_50_mm']:+.2f}/"
                 f"{s['point_10_mm'] - t['point_10_mm']:+.2f}/"
                 f"{s['point_2_mm'] - t['point_2_mm']:+.2f} mm from the truth's "
                 f"({t['point_50_mm']:.2f}/{t['point_10_mm']:.2f}/{t['point_2_mm']:.2f}); "
                 f"past the terminator "
                 f"{s['past_terminator'] / max(t['past_terminator'], 1e-12):.2f} of the truth")
    return line


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", default=str(ROOT / "benchmarks" / "results" /
                                                      "curved.json"))
    args = parser.parse_args()
    variant, why = mono_variant()
    print(f"Mitsuba: {variant or 'left out'} ({why})")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for radius, angle in CASES:
            rgb = sphere_render(Path(tmp), radius, angle)
            width = 2.4 * radius
            row: dict = {"radius_mm": radius, "angle_deg": angle,
                         "seam_step": _worst_step(rgb, width, radius, angle).round(4).tolist()}
            line = f"R {radius:g} mm, {angle:g} deg: seam step {row['seam_step']}"
            if variant is not None and angle > 0:  # at 0 the terminator is the rim
                truth = mitsuba_strip(variant, radius, angle)
                row["figures"] = strip_figures(rgb, truth, radius, angle)
                without = sphere_render(Path(tmp), radius, angle, "--no-transmission")
                row["without_transmission"] = strip_figures(without, truth, radius, angle)
                line += figures_line(row["figures"]) + "\n without transmission:" \
                    + figures_line(row["without_transmission"])
            rows.append(row)
            print(line, flush=True)
    out = Path(args.output)
    out.write_text(json.dumps({"mitsuba_variant": variant, "mitsuba_spp": SPP,
                               "mitsuba_note": why, "rows": rows}, indent=1) + "\n")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
