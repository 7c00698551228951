"""A sphere of skin1 rendered the user's way, and where its terminator lies: what
tests/render/light/test_first_scatter.py and benchmarks/bench_curved.py hold against
Mitsuba 3's path-traced sphere (fixtures/physics/sphere_terminator.json)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import UsdGeom

from ..render_scenes import (
    distant_down,
    ortho_camera_down,
    paint_skin1_albedo,
    render_diffuse,
    scene_over,
    skin1_asset,
)
from .diffusion.test_curved_seams import _sphere


def sphere_render(tmp: Path, radius_mm: float, angle_deg: float, *extra: str) -> np.ndarray:
    """The diffuse AOV (512 x 512 over 2.4 radii) of skinpipe's sphere, RGB; ``extra``:
    more options for ``render``."""
    mesh = _sphere(radius_mm)
    obj = tmp / f"sphere_{radius_mm:g}.obj"
    tri = mesh.face_indices.reshape(-1, 3) + 1
    obj.write_text("".join(f"v {a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in mesh.points)
                   + "".join(f"f {a} {b} {c}\n" for a, b, c in tri))
    asset = skin1_asset(tmp, obj, [0.0, 0.0, radius_mm], tmp / f"asset_{radius_mm:g}")
    width = 2.4 * radius_mm

    def build(stage) -> None:
        ortho_camera_down(stage, width, width)
        UsdGeom.Xformable(distant_down(stage)).AddRotateYOp().Set(angle_deg)
        paint_skin1_albedo(stage)

    scene = scene_over(asset / "asset.usda", tmp / f"scene_{radius_mm:g}_{angle_deg:g}.usda",
                       build)
    out = tmp / f"out_{radius_mm:g}_{angle_deg:g}{''.join(extra)}"
    return render_diffuse(scene, out, "--resolution", "512x512", "--texture-size", "1024",
                          "--rho-s", "0", "--ior", "1", *extra)


def terminator_figures(x: np.ndarray, level: np.ndarray, terminator_mm: float
                       ) -> dict[str, float]:
    """The centre's level, where the light falls to 50%, 10% and 2% of it on the
    terminator's side (x < 0), and the mean light 1-2 mm beyond the terminator."""
    centre = float(np.interp(0.0, x, level))
    out = {"centre": centre}
    for share in (0.5, 0.1, 0.02):
        below = np.flatnonzero((x < 0) & (level < share * centre))
        i = int(below.max()) if below.size else 0
        x0, x1, a0, a1 = x[i], x[i + 1], level[i], level[i + 1]
        out[f"point_{round(share * 100)}_mm"] = float(
            x0 + (share * centre - a0) / (a1 - a0) * (x1 - x0)) if a1 != a0 else float(x0)
    past = (x < terminator_mm - 1.0) & (x > terminator_mm - 2.0)
    out["past_terminator"] = float(level[past].mean())
    return out
