"""Light across UV seams on a curved surface unwrapped by xatlas as it comes: a sphere of
radius 10 mm, lit by a distant light at 60 degrees, one Gaussian term of the diffusion
against the same Gaussian of the geodesic distance summed over the surface by brute
force (what the chart tiles approximate), and through the CLI a rendered sphere."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pymeshlab
import pytest

from skinpipe.cli import main
from skinpipe.render.device.choice import open_device
from skinpipe.render.diffusion.diffuse import diffuse
from skinpipe.render.diffusion.layout import chart_layout
from skinpipe.render.light.raytrace import RayScene
from skinpipe.render.surface.texture_maps import rasterize
from skinpipe.render.surface.unwrap import diffusion_chart_area, triangulate, unwrap
from skinpipe.usd.mesh import MeshData

from ...render_scenes import distant_down, ortho_camera_down, render_diffuse, scene_over

PHYSICS = Path(__file__).parents[2] / "fixtures" / "physics"
RADIUS_MM = 10.0
CYLINDER_MM = 5.0
SIGMA_MM = 2.0


def _sphere(radius_mm: float) -> MeshData:
    ms = pymeshlab.MeshSet()
    ms.create_sphere(radius=radius_mm, subdiv=5)
    m = ms.current_mesh()
    faces = np.asarray(m.face_matrix(), np.int32)
    return MeshData(np.asarray(m.vertex_matrix(), np.float64),
                    np.full(len(faces), 3, np.int32), faces.reshape(-1), 0.001)


def _cylinder(radius_mm: float, length_mm: float = 40.0) -> MeshData:
    """An open tube along y, 128 segments round, rows about as long as a segment."""
    segments = 128
    rows = int(length_mm / (2 * math.pi * radius_mm / segments))
    phi = np.arange(segments) * 2 * math.pi / segments
    y = np.linspace(-length_mm / 2, length_mm / 2, rows + 1)
    points = np.stack([np.tile(radius_mm * np.sin(phi), rows + 1), np.repeat(y, segments),
                       np.tile(radius_mm * np.cos(phi), rows + 1)], axis=1)
    faces = []
    for r in range(rows):
        for c in range(segments):
            a, b = r * segments + c, r * segments + (c + 1) % segments
            faces += [[a, b + segments, b], [a, a + segments, b + segments]]
    faces_a = np.asarray(faces, np.int32)
    return MeshData(points, np.full(len(faces_a), 3, np.int32), faces_a.reshape(-1), 0.001)


def _sphere_geodesic(p_src: np.ndarray, p: np.ndarray) -> np.ndarray:
    return RADIUS_MM * np.arccos(np.clip(p_src @ p / RADIUS_MM**2, -1.0, 1.0))


def _cylinder_geodesic(p_src: np.ndarray, p: np.ndarray) -> np.ndarray:
    turn = np.arctan2(p_src[:, 0], p_src[:, 2]) - math.atan2(p[0], p[2])
    turn = np.abs((turn + math.pi) % (2 * math.pi) - math.pi)
    return np.hypot(CYLINDER_MM * turn, p_src[:, 1] - p[1])


def _largest_error(mesh: MeshData, geodesic: Callable[[np.ndarray, np.ndarray], np.ndarray],
                   min_chart_area: float, away_from_ends_mm: float = np.inf
                   ) -> tuple[float, int]:
    """The largest difference of the diffused light from the geodesic Gaussian's, over
    500 fully covered texels (the lit level is 1; on a tube only those farther than
    ``away_from_ends_mm`` from its open ends' plane y = +-20 are judged, where the
    normalised convolution truncates the profile), and the number of charts."""
    layout = unwrap(mesh, min_chart_area=min_chart_area)
    tris, uv_tris = triangulate(mesh), layout.uv_indices.reshape(-1, 3)
    maps = rasterize(mesh.points, tris, layout.uv, uv_tris, 512, 0.001)
    charts = chart_layout(open_device(), maps, mesh.points, tris, layout.uv, uv_tris,
                          RayScene([(mesh.points, tris)]), 0)
    cov = maps.coverage
    light = np.array([math.sin(math.radians(60)), 0.0, math.cos(math.radians(60))])
    e = np.clip(maps.normal @ light, 0.0, None) * (cov > 0)
    out, _ = diffuse(np.repeat(e[..., None], 3, axis=2).astype(np.float32),
                     maps.mm_per_texel_u, maps.mm_per_texel_v, cov,
                     np.array([SIGMA_MM**2]), np.ones((1, 1, 3)), charts=charts)
    source = np.argwhere(cov > 0)
    p_src = maps.position[source[:, 0], source[:, 1]].astype(np.float64)
    weight = (maps.mm_per_texel_u * maps.mm_per_texel_v * cov)[source[:, 0], source[:, 1]]
    e_src = e[source[:, 0], source[:, 1]]
    full = np.argwhere(cov > 0.999)
    full = full[20.0 - np.abs(maps.position[full[:, 0], full[:, 1], 1]) > away_from_ends_mm] \
        if np.isfinite(away_from_ends_mm) else full
    worst = 0.0
    for i, j in full[np.random.default_rng(0).choice(len(full), 500, replace=False)]:
        g = np.exp(-0.5 * (geodesic(p_src, maps.position[i, j].astype(np.float64))
                           / SIGMA_MM) ** 2) * weight
        worst = max(worst, abs(float(out[i, j, 0]) - float(g @ e_src / g.sum())))
    return worst, layout.charts


def test_charts_made_for_diffusion_carry_light_across_seams_on_a_sphere() -> None:
    """xatlas's area cap (a hundredth of the mesh) cuts the sphere into 148 charts of
    3.5 mm, too narrow for the term: their margins read little at its pyramid level and
    the light is off by up to 23% of the lit level. Charts no smaller than (8 sigma)^2:
    within 1.1%."""
    worst, charts = _largest_error(_sphere(RADIUS_MM), _sphere_geodesic,
                                   diffusion_chart_area(SIGMA_MM**2, 0.001))
    assert charts < 20 and worst < 0.02, (charts, worst)
    assert diffusion_chart_area(1.0, 0.01) == pytest.approx(0.64)  # cm: 8 mm = 0.8 cm


def test_charts_made_for_diffusion_carry_light_round_a_tube() -> None:
    """A tube of radius 5 mm, 40 mm long, unwrapped by xatlas as it comes: capped at a
    hundredth (128 charts) 78% of the lit level off, at (4 sigma)^2 cut into rings 1.4 mm
    long (28 charts) 44% off, at (8 sigma)^2 (6 charts) within 0.8%, judged farther than
    3 sigma from its open ends."""
    worst, charts = _largest_error(_cylinder(CYLINDER_MM), _cylinder_geodesic,
                                   diffusion_chart_area(SIGMA_MM**2, 0.001), 3 * SIGMA_MM)
    assert charts < 20 and worst < 0.02, (charts, worst)


def _worst_step(diffuse_rgb: np.ndarray, width_mm: float, radius_mm: float = RADIUS_MM,
                light_deg: float = 0.0) -> np.ndarray:
    """Per channel the largest jump between adjacent pixels beyond what their
    neighbours' steps say (a step at a seam), over the sphere's face (radius < 0.9 R,
    above 2% of the channel's peak, away from the terminator's kink: |n.l| > 0.2 for a
    light ``light_deg`` off the camera's axis towards +x) where the light changes by
    less than 1% a pixel."""
    w = diffuse_rgb.shape[1]
    x = (np.arange(w) + 0.5) / w * width_mm - width_mm / 2
    xx, yy = np.meshgrid(x, x[::-1])
    inside = xx**2 + yy**2 < (0.9 * radius_mm) ** 2
    zz = np.sqrt(np.clip(radius_mm**2 - xx**2 - yy**2, 0.0, None))
    theta = math.radians(light_deg)
    inside &= np.abs(xx * math.sin(theta) + zz * math.cos(theta)) > 0.2 * radius_mm
    return _worst_step_in(diffuse_rgb, inside)


def _worst_step_in(diffuse_rgb: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """:func:`_worst_step` over the pixels ``inside`` (H, W)."""
    worst = np.zeros(3)
    for c in range(3):
        a = diffuse_rgb[..., c].astype(np.float64)
        lit = inside & (a > 0.02 * a[inside].max())
        for img, mask in ((a, lit), (a.T, lit.T)):
            step = np.diff(img, axis=1)
            expected = 0.5 * (np.roll(step, 1, axis=1) + np.roll(step, -1, axis=1))
            level = np.maximum(img[:, 1:], 1e-12)
            ok = mask[:, 1:] & mask[:, :-1] & np.roll(mask[:, 1:], 1, axis=1) \
                & np.roll(mask[:, 1:], -1, axis=1) & (np.abs(expected) / level < 0.01)
            ok[:, 0] = ok[:, -1] = False
            worst[c] = max(worst[c], float((np.abs(step - expected) / level)[ok].max()))
    return worst


@pytest.mark.slow  # a fit, an unwrap and a render: about 20 s
def test_a_rendered_sphere_shows_no_seam(tmp_path: Path) -> None:
    """The user's road: skin1's profile CSV through ``fit``, a sphere without UVs through
    ``author`` and ``render`` (xatlas as it comes), lit from straight above. With the
    area cap alone the seams stepped by 19% in red."""
    mesh = _sphere(RADIUS_MM)
    obj = tmp_path / "sphere.obj"
    tri = mesh.face_indices.reshape(-1, 3) + 1
    obj.write_text("".join(f"v {a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in mesh.points)
                   + "".join(f"f {a} {b} {c}\n" for a, b, c in tri))
    fits = tmp_path / "fits"
    fits.mkdir()
    assert main(["fit", str(PHYSICS / "skin1.csv"), "-k", "6",
                 "-o", str(fits / "skin1.json")]) == 0
    landmarks = tmp_path / "landmarks.json"
    landmarks.write_text(json.dumps({"regions": {"skin1": [[0.0, 0.0, RADIUS_MM]]}}))
    asset = tmp_path / "asset"
    assert main(["author", "--fits", str(fits), "--mesh", str(obj), "--landmarks",
                 str(landmarks), "-o", str(asset)]) == 0
    width = 2.4 * RADIUS_MM

    def build(stage) -> None:
        ortho_camera_down(stage, width, width)
        distant_down(stage)

    scene = scene_over(asset / "asset.usda", tmp_path / "scene.usda", build)
    out = tmp_path / "out"
    rgb = render_diffuse(scene, out, "--resolution", "512x512", "--texture-size", "1024",
                         "--rho-s", "0")
    worst = _worst_step(rgb, width)
    assert np.all(worst < 0.02), worst.round(4).tolist()


@pytest.mark.slow  # a fit, an unwrap and a render: about 25 s
def test_a_rendered_tube_shows_no_seam(tmp_path: Path) -> None:
    """The user's road on a cylinder: a tube of radius 5 mm through ``author`` (xatlas as
    it comes) and ``render`` with skin1's fit (red reaches 9 mm), lit at 60 degrees
    across it, seen from above over its middle 12 mm: no channel steps by 1% where the
    light is smooth (0.03-0.04%; blurred in the chart tiles, red stepped by 4.0%)."""
    from ...render_scenes import skin1_asset

    mesh = _cylinder(CYLINDER_MM)
    obj = tmp_path / "tube.obj"
    tri = mesh.face_indices.reshape(-1, 3)[:, ::-1] + 1  # wound to face outwards
    obj.write_text("".join(f"v {a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in mesh.points)
                   + "".join(f"f {a} {b} {c}\n" for a, b, c in tri))
    asset = skin1_asset(tmp_path, obj, [0.0, 0.0, CYLINDER_MM], tmp_path / "asset")
    width, angle = 2.4 * CYLINDER_MM, 60.0

    def build(stage) -> None:
        from pxr import UsdGeom

        ortho_camera_down(stage, width, width)
        UsdGeom.Xformable(distant_down(stage)).AddRotateYOp().Set(angle)

    scene = scene_over(asset / "asset.usda", tmp_path / "scene.usda", build)
    rgb = render_diffuse(scene, tmp_path / "out", "--resolution", "512x512",
                         "--texture-size", "1024", "--rho-s", "0", "--ior", "1")
    x = (np.arange(rgb.shape[1]) + 0.5) / rgb.shape[1] * width - width / 2
    xx = np.broadcast_to(x, rgb.shape[:2])
    nz = np.sqrt(np.clip(1.0 - (xx / CYLINDER_MM) ** 2, 0.0, None))
    theta = math.radians(angle)
    inside = (np.abs(xx) < 0.9 * CYLINDER_MM) & (
        np.abs(xx / CYLINDER_MM * math.sin(theta) + nz * math.cos(theta)) > 0.2)
    worst = _worst_step_in(rgb, inside)
    assert np.all(worst < 0.01), worst.round(4).tolist()
