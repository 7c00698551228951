"""Light through thin parts (skinpipe/render/light/thin_parts.py) against the independent
light tracer (tests/physics/light_tracer.py, ``trace_slab_from_below``: an index-matched
slab of skin1 lit uniformly from behind, seen from straight above; Mitsuba 3's volpath
gives the same to 0.3%): the table alone, and through the CLI a slab mesh lit from
behind, the profile taking the user's road (skin1's traced CSV through ``skinpipe fit``
at its defaults, ``author`` without UVs, ``render``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import UsdGeom

from skinpipe.render.light.thin_parts import slab_transmission

from ...physics.light_tracer import medium, trace_slab_from_below
from ...render_scenes import (
    distant_down,
    ortho_camera_down,
    paint_skin1_albedo,
    render_diffuse,
    scene_over,
    skin1_asset,
)

SIDE_MM = 40.0


def _truth(thickness_mm: float, photons: int = 100_000) -> np.ndarray:
    """The up-radiance above the slab per unit irradiance from below, R, G, B."""
    return np.array([trace_slab_from_below(medium("skin1", c), thickness_mm, photons,
                                           seed=11 + c) for c in range(3)])


@pytest.mark.parametrize("thickness_mm", [0.5, 2.0, 5.0])
def test_the_table_gives_the_tracers_transmission(thickness_mm: float) -> None:
    s = np.array([0.74, 0.88, 1.01])
    a = np.array([0.032, 0.17, 0.48])
    got = slab_transmission(s / (s + a), (s + a) * thickness_mm) / math.pi
    np.testing.assert_allclose(got, _truth(thickness_mm), rtol=0.06)


def _slab_obj(path: Path, thickness_mm: float, n: int = 16) -> Path:
    """A closed box SIDE_MM wide and ``thickness_mm`` thick, top face at z = 0, outward
    faces, without UVs."""
    xs = np.linspace(-SIDE_MM / 2, SIDE_MM / 2, n + 1)
    verts: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []

    def grid(z: float, up: bool) -> None:
        base = len(verts)
        verts.extend((x, y, z) for y in xs for x in xs)
        for r in range(n):
            for c in range(n):
                a = base + r * (n + 1) + c
                quad = (a, a + 1, a + n + 2, a + n + 1)
                faces.extend([(quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])]
                             if up else [(quad[0], quad[2], quad[1]), (quad[0], quad[3], quad[2])])

    grid(0.0, True)
    grid(-thickness_mm, False)
    top, bottom = 0, (n + 1) ** 2
    ring = [r * (n + 1) + c for r, c in
            [(0, c) for c in range(n)] + [(r, n) for r in range(n)]
            + [(n, c) for c in range(n, 0, -1)] + [(r, 0) for r in range(n, 0, -1)]]
    for i, a in enumerate(ring):  # the sides, outward with the ring counter-clockwise
        b = ring[(i + 1) % len(ring)]
        faces.extend([(top + a, bottom + a, bottom + b), (top + a, bottom + b, top + b)])
    path.write_text("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in verts)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in faces))
    return path


def _rendered_transmission(tmp: Path, thickness_mm: float, *extra: str,
                           texture: int = 512) -> np.ndarray:
    """The diffuse radiance at the top's centre, R, G, B, under unit irradiance from
    below, the slab's albedo skin1's measured one."""
    asset = skin1_asset(tmp, _slab_obj(tmp / f"slab_{thickness_mm:g}.obj", thickness_mm),
                        [0.0, 0.0, 0.0], tmp / f"asset_{thickness_mm:g}")

    def build(stage) -> None:
        ortho_camera_down(stage, 8.0, 8.0)
        light = distant_down(stage)
        UsdGeom.Xformable(light).AddRotateXOp().Set(180.0)  # shining up, from behind
        paint_skin1_albedo(stage)

    scene = scene_over(asset / "asset.usda", tmp / f"scene_{thickness_mm:g}.usda", build)
    out = tmp / f"out_{thickness_mm:g}_{texture}"
    rgb = render_diffuse(scene, out, "--resolution", "16x16", "--texture-size", str(texture),
                         "--rho-s", "0", "--ior", "1", *extra)
    return rgb[6:10, 6:10].mean(axis=(0, 1)).astype(np.float64)


@pytest.mark.slow  # a fit, two authors and four renders: about 30 s
def test_a_slab_lit_from_behind_lets_through_what_the_tracer_does(tmp_path: Path) -> None:
    """2 and 5 mm of skin1: within 10% per channel (the light that reaches the top is
    the transmitted light alone: the top is unlit). Without transmission: nothing but
    what creeps round the slab's sides from 20 mm away. At texture 2048 the far sides
    are found by probing blocks first (thin_parts.PROBE_TEXTURE_SIZE): the 2 mm slab
    holds as well."""
    for thickness, texture in ((2.0, 512), (5.0, 512), (2.0, 2048)):
        got = _rendered_transmission(tmp_path, thickness, texture=texture)
        want = _truth(thickness)
        assert np.all(np.abs(got / want - 1) < 0.10), (thickness, texture, got / want)
    dark = _rendered_transmission(tmp_path, 2.0, "--no-transmission")
    assert np.all(dark < 1e-3 * _truth(2.0)), dark  # what creeps round the slab's sides


def test_rays_into_the_skin_go_in_bands_and_keep_only_far_sides(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """back_points casts its rays a band of points at a time and keeps only the points
    with a far side: a closed box 2 mm thick, its top's points over half of it, banded 7
    at a time, finds the same points, triangles, barycentrics and thicknesses as in one
    band; a point off the box finds none."""
    from skinpipe.render.light import thin_parts
    from skinpipe.render.light.raytrace import RayScene

    corners = np.array([[x, y, z] for z in (0.0, 2.0) for y in (0.0, 10.0) for x in (0.0, 10.0)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    tris = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    rays = RayScene([(corners, tris)])
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(0.5, 19.5, 40), rng.uniform(0.5, 9.5, 40),
                              np.full(40, 2.0)])
    normals = np.tile([0.0, 0.0, 1.0], (40, 1))
    whole = thin_parts.back_points(rays, 0, corners, tris, points, normals, 5.0)
    monkeypatch.setattr(thin_parts, "BAND_POINTS", 7)
    banded = thin_parts.back_points(rays, 0, corners, tris, points, normals, 5.0)
    for a, b in zip(whole, banded, strict=True):
        np.testing.assert_array_equal(a, b)
    index, _, _, thickness = banded
    np.testing.assert_array_equal(index, np.flatnonzero(points[:, 0] < 10.0))
    np.testing.assert_allclose(thickness, 2.0, rtol=1e-4)  # from the offset origin


def test_a_ball_is_round_and_a_slab_flat() -> None:
    """flatness: a chord tilted 45 degrees from -n is d / cos through a slab and d cos
    through a ball; the slab's light goes through it (1), the ball's goes round its
    surface, which the diffusion carries already (0: with the slab's transmission a
    5 mm sphere of skin1 lit at 60 degrees had 2.3x the path tracer's red light past
    its terminator)."""
    from skinpipe.render.light import thin_parts
    from skinpipe.render.light.raytrace import RayScene

    from ..diffusion.test_curved_seams import _sphere

    corners = np.array([[x, y, z] for z in (0.0, 2.0) for y in (0.0, 20.0) for x in (0.0, 20.0)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    box = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    top = np.array([[10.0, 10.0, 2.0], [5.0, 12.0, 2.0]])
    up = np.tile([0.0, 0.0, 1.0], (2, 1))
    flat = thin_parts.flatness(RayScene([(corners, box)]), 0, corners, box, top, up,
                               np.full(2, 2.0))
    np.testing.assert_allclose(flat, 1.0, atol=1e-4)  # the rays start a float step in
    ball = _sphere(5.0)
    tris = ball.face_indices.reshape(-1, 3)
    rng = np.random.default_rng(2)
    n = rng.normal(size=(20, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    round_ = thin_parts.flatness(RayScene([(ball.points, tris)]), 0, ball.points, tris,
                                 4.99 * n, n, np.full(20, 10.0))  # within the facets
    assert np.all(round_ < 0.02), round_


def test_probing_blocks_finds_the_far_sides_every_texel_finds(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A closed box 10 x 10 x 2 mm unwrapped by xatlas, at texture 1024 with blocks of 8
    texels probed first: the same far sides, far texels and factors as rays from every
    texel, from fewer rays (the sides, 10 mm across, have none within the 3.3 mm reach)."""
    from skinpipe.render.light import thin_parts
    from skinpipe.render.light.raytrace import RayScene
    from skinpipe.render.surface.texture_maps import rasterize
    from skinpipe.render.surface.unwrap import triangulate, unwrap
    from skinpipe.usd.mesh import MeshData

    box = np.array([[x, y, z] for z in (0.0, 2.0) for y in (0.0, 10.0) for x in (0.0, 10.0)])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    corners = box[np.ravel(quads)]  # each face its own corners: flat normals
    tris = np.array([(4 * q, 4 * q + 1 + k, 4 * q + 2 + k) for q in range(6) for k in (0, 1)],
                    np.int32)
    mesh = MeshData(corners, np.full(len(tris), 3, np.int32), tris.reshape(-1), 0.001)
    layout = unwrap(mesh)
    uv_tris = layout.uv_indices.reshape(-1, 3)
    maps = rasterize(corners, triangulate(mesh), layout.uv, uv_tris, 1024, 0.001)
    texel = np.flatnonzero(maps.coverage.ravel() > 0)
    points = maps.position.reshape(-1, 3)[texel]
    normals = maps.normal.reshape(-1, 3)[texel]
    media = thin_parts.ThinMedia(np.full((1, 3), 0.9), np.full((1, 3), 4.0), np.ones(3))
    assert 3.0 < media.reach < 5.0

    cast = thin_parts.back_points
    counted = [0]

    def counting(*args: object) -> tuple[np.ndarray, ...]:
        counted[0] += len(args[4])  # type: ignore[arg-type]
        return cast(*args)  # type: ignore[arg-type]

    monkeypatch.setattr(thin_parts, "back_points", counting)

    def far(probe_size: int) -> tuple[thin_parts.FarSide, int]:
        monkeypatch.setattr(thin_parts, "PROBE_TEXTURE_SIZE", probe_size)
        counted[0] = 0
        got = thin_parts.far_side(RayScene([(corners, tris)]), 0, corners, tris, layout.uv,
                                  uv_tris, 1024, points, normals, texel, media, None)
        return got, counted[0]

    (every, every_rays), (probed, probed_rays) = far(1024), far(128)
    assert 0.5 * texel.size < every.rows.size < 0.8 * texel.size
    for a, b in ((every.rows, probed.rows), (every.far_rows, probed.far_rows),
                 (every.factor, probed.factor)):
        np.testing.assert_array_equal(a, b)
    assert probed_rays < 0.9 * every_rays, (probed_rays, every_rays)
