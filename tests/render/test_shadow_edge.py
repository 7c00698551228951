"""A hard shadow edge through the diffusion, against its analytic spread, measured
through ``skinpipe render`` only (its texture-space radiosity output).

A flat patch under a distant light of angle 0, half of it shaded by a blocker hidden
from the camera: the irradiance is E0 H(x), and diffused by a profile sum_i w_i G(v_i)
the radiosity is rho E0 sum_i w_i Phi(x / sqrt(v_i)) (Phi the normal CDF), for
variances 0.05, 0.5 and 4 mm^2. Checked at the default texture size and shadow
sampling, on an unstretched UV layout and one stretched 3x, the edge across u and
across v (issue 19: within 1% in the L2 sense of eq. 2c, 1.5% of the plateau
pointwise, 5% in the derivative).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from pxr import Gf, UsdGeom
from scipy.special import ndtr

from skinpipe.cli import main
from skinpipe.usd.author import RegionAssignment, author_asset
from skinpipe.usd.mesh import MeshData

from ..render_scenes import distant_down, exact_fit, hidden_blocker, ortho_camera_down, scene_over

VARIANCES_MM2 = (0.05, 0.5, 4.0)
WEIGHTS = (0.3, 0.4, 0.3)
TEXTURE = 1024  # the default


def _patch(out: Path, size_u_mm: float, size_v_mm: float, n: int = 24) -> Path:
    """A flat patch in z = 0, ``size_u_mm`` along x (u) by ``size_v_mm`` along y (v),
    its UVs the unit square: a 3x stretch is a patch three times longer along one axis."""
    us, vs = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    uv = np.stack([us.ravel(), vs.ravel()], axis=1)
    pts = np.stack([(uv[:, 0] - 0.5) * size_u_mm, (uv[:, 1] - 0.5) * size_v_mm,
                    np.zeros(uv.shape[0])], axis=1)
    tris = []
    for r in range(n):
        for c in range(n):
            a = r * (n + 1) + c
            tris += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    tris = np.asarray(tris, np.int32)
    mesh = MeshData(pts, np.full(tris.shape[0], 3, np.int32), tris.reshape(-1), 0.001, uv)
    fit = exact_fit("skin", VARIANCES_MM2, np.tile(np.asarray(WEIGHTS)[:, None], (1, 3)))
    regions = RegionAssignment(("skin",), np.zeros(tris.shape[0], np.int32),
                               np.ones((pts.shape[0], 1), np.float32))
    return author_asset([fit], mesh, regions, out, name="Patch", up_axis="Z").asset


def _scene(tmp: Path, asset: Path, across: str, far_object: bool = False) -> Path:
    """The light straight down; a blocker at z = 10 over x < 0 (edge across u) or y < 0
    (across v), hidden from the camera; an orthographic camera looking down."""

    def build(stage) -> None:
        ortho_camera_down(stage, 150.0, 150.0)
        distant_down(stage, intensity=1.0, angle=0.0)
        big = 500.0
        hidden_blocker(stage, [(-big, -big), (0, -big), (0, big), (-big, big)] if across == "u"
                       else [(-big, -big), (big, -big), (big, 0), (-big, 0)])
        if far_object:  # a 10 m box far away: it must move no shadow
            far = UsdGeom.Cube.Define(stage, "/Far")
            far.CreateSizeAttr(10000.0)
            UsdGeom.Xformable(far).AddTranslateOp().Set(Gf.Vec3d(60000, 0, -20000))

    return scene_over(asset, tmp / f"scene_{across}{'_far' if far_object else ''}.usda",
                      build)


def _radiosity_profile(exr: Path, across: str, size_mm: float
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Positions (mm) and the radiosity (mean of R, G, B over the middle half of the
    lines parallel to the edge) across the edge."""
    buf = oiio.ImageBuf(str(exr))
    names = list(buf.spec().channelnames)
    px = np.asarray(buf.get_pixels(oiio.FLOAT))[::-1]  # row 0 back to v = 0
    rad = np.mean([px[..., names.index(f"radiosity.{c}")] for c in "RGB"], axis=0)
    n = rad.shape[0]
    keep = slice(n // 4, 3 * n // 4)
    line = rad[keep, :].mean(axis=0) if across == "u" else rad[:, keep].mean(axis=1)
    x = ((np.arange(n) + 0.5) / n - 0.5) * size_mm
    return x, line


def _analytic(x: np.ndarray) -> np.ndarray:
    return sum(w * ndtr(x / np.sqrt(v)) for v, w in zip(VARIANCES_MM2, WEIGHTS, strict=True))


def _render(tmp: Path, scene: Path, name: str) -> Path:
    out = tmp / f"out_{name}"
    assert main(["render", str(scene), "-o", str(out), "--resolution", "32x32",
                 "--aovs", "beauty", "--texture-outputs", "radiosity"]) == 0
    return out / f"{scene.stem}_uv.exr"


@pytest.mark.parametrize("stretch", [1.0, 3.0], ids=["unstretched", "stretched3x"])
@pytest.mark.parametrize("across", ["u", "v"])
def test_a_hard_shadow_edge_follows_its_analytic_spread(tmp_path: Path, stretch: float,
                                                        across: str) -> None:
    size = 40.0 * stretch  # along the axis the edge profile runs
    size_u, size_v = (size, 40.0) if across == "u" else (40.0, size)
    asset = _patch(tmp_path / "asset", size_u, size_v)
    exr = _render(tmp_path, _scene(tmp_path, asset, across), across)
    x, line = _radiosity_profile(exr, across, size)
    plateau = float(np.median(line[x > 12.0]))  # 6 sigma of the widest term from the edge
    assert plateau > 0
    f, g = line / plateau, _analytic(x)
    window = np.abs(x) < 12.0
    l2 = np.sqrt(np.sum((f - g)[window] ** 2) / np.sum(g[window] ** 2))
    pointwise = np.abs(f - g)[window].max()
    df, dg = np.gradient(f, x), np.gradient(g, x)
    derivative = np.abs(df - dg)[window].max() / dg.max()
    assert l2 < 0.01, (l2, pointwise, derivative)
    assert pointwise < 0.015, (l2, pointwise, derivative)
    assert derivative < 0.05, (l2, pointwise, derivative)


def test_a_far_object_does_not_move_the_diffused_edge(tmp_path: Path) -> None:
    asset = _patch(tmp_path / "asset", 40.0, 40.0)
    near = _radiosity_profile(_render(tmp_path, _scene(tmp_path, asset, "u"), "near"),
                              "u", 40.0)[1]
    far = _radiosity_profile(_render(tmp_path, _scene(tmp_path, asset, "u", True), "far"),
                             "u", 40.0)[1]
    # the edge's position: where the profile crosses half its plateau, in texels
    def crossing(line: np.ndarray) -> float:
        half = 0.5 * np.median(line[-100:])
        i = int(np.flatnonzero(line >= half)[0])
        return i - 1 + (half - line[i - 1]) / (line[i] - line[i - 1])

    assert abs(crossing(near) - crossing(far)) < 0.1
