"""Regenerate tests/fixtures/physics/sphere_terminator.json with Mitsuba 3.

    python tools/trace_sphere_terminator.py   (about two minutes on two cores; needs the
    ``bench`` extra, and Mitsuba's LLVM variant a libLLVM it can use)

The path-traced truth the terminator tests read: a sphere of skin1 (Jensen et al. 2001,
index-matched, isotropic) of radius 10 mm and 5 mm under a distant light at 60 degrees
towards +x, seen from straight above by an orthographic camera; Mitsuba's ``volpath``,
one monochrome render a channel, the radiance along a strip 4 pixels high through the
centre (benchmarks/bench_curved.py renders it the same way).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.bench_curved import SKIN1, STRIP, mitsuba_strip  # noqa: E402
from benchmarks.bench_mitsuba import mono_variant  # noqa: E402

OUT = ROOT / "tests" / "fixtures" / "physics" / "sphere_terminator.json"
CASES = ((10.0, 60.0), (5.0, 60.0))
SPP = 16384


def main() -> None:
    variant, why = mono_variant()
    if variant is None or "llvm" not in variant:
        sys.exit(f"needs Mitsuba's LLVM variant: {why}")
    rows = []
    for radius, angle in CASES:
        strip = mitsuba_strip(variant, radius, angle, SPP)
        x = ((np.arange(STRIP[0]) + 0.5) / STRIP[0] * 2 - 1) * 1.2 * radius
        rows.append({"radius_mm": radius, "light_deg": angle, "x_mm": x.round(5).tolist(),
                     "radiance": [[float(f"{v:.5g}") for v in c] for c in strip]})
        print(f"R {radius:g} mm, {angle:g} deg", flush=True)
    OUT.write_text(json.dumps({
        "source": "Mitsuba 3 volpath (tools/trace_sphere_terminator.py)",
        "variant": variant, "spp": SPP, "medium": {"sigma_s_per_mm": SKIN1[0],
                                                   "sigma_a_per_mm": SKIN1[1]},
        "irradiance": 1.0, "rows": rows}, indent=1) + "\n")
    print(f"wrote {OUT}")


if __name__ == "__main__":
    main()
