"""UV rasterisation and unwrapping: analytic references on flat patches; the OpenCL
rasteriser against the numpy reference (overlaps, degenerate and outside triangles)."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.errors import InputError, SkinpipeError
from skinpipe.render.surface.texture_maps import (
    TextureMaps,
    at_texels,
    rasterize,
    rasterize_reference,
    texels_in_blocks,
)
from skinpipe.render.surface.unwrap import triangulate, unwrap
from skinpipe.usd.mesh import MeshData

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


def _cells(n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit square's UVs on an (n_u + 1) x (n_v + 1) grid and its two triangles a
    cell."""
    xs, ys = np.meshgrid(np.linspace(0, 1, n_u + 1), np.linspace(0, 1, n_v + 1))
    uv = np.stack([xs.ravel(), ys.ravel()], axis=1)
    tris = []
    for r in range(n_v):
        for c in range(n_u):
            a = r * (n_u + 1) + c
            tris += [[a, a + 1, a + n_u + 2], [a, a + n_u + 2, a + n_u + 1]]
    return uv, np.array(tris, np.int32)


def _grid(n: int, size_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    uv, tris = _cells(n, n)
    pts = np.stack([uv[:, 0] * size_mm, uv[:, 1] * size_mm, np.zeros(uv.shape[0])], axis=1)
    return pts, tris, uv


@pytest.mark.parametrize(("shape", "block"), [((8, 8), 4), ((5, 7), 2), ((33, 65), 32),
                                               ((1, 3), 32)])
def test_texels_in_blocks_is_every_covered_texel_block_by_block(
        shape: tuple[int, int], block: int) -> None:
    covered = np.random.default_rng(3).random(shape) < 0.6
    texel = texels_in_blocks(covered, block)
    np.testing.assert_array_equal(np.sort(texel), np.flatnonzero(covered))
    # by block row, block column, then row and column in the block
    y, x = np.divmod(texel, shape[1])
    key = np.stack([y // block, x // block, y % block, x % block])
    assert np.all(np.diff(np.ravel_multi_index(key, (shape[0], shape[1], block, block))) > 0)


@pytest.mark.parametrize(("su", "sv"), [(1.0, 1.0), (0.5, 1.0), (0.25, 0.8)])
def test_stretch_is_mm_per_texel(su: float, sv: float) -> None:
    pts, tris, uv = _grid(8, 100.0)
    maps = rasterize(pts, tris, uv * [su, sv], tris, 256, 0.001)
    cov = maps.coverage > 0
    # a 100 mm patch on su x 256 texels: 100 / (su 256) mm per texel along u
    np.testing.assert_allclose(maps.mm_per_texel_u[cov], 100.0 / (su * 256), rtol=1e-5)
    np.testing.assert_allclose(maps.mm_per_texel_v[cov], 100.0 / (sv * 256), rtol=1e-5)
    assert abs(cov.mean() - su * sv) < 0.02
    # as the seam layout reads them, from the triangles: the same analytic sizes
    u, v = maps.triangle_stretch()
    box = (slice(None), slice(None))
    np.testing.assert_allclose(u[box][cov], 100.0 / (su * 256), rtol=1e-5)
    np.testing.assert_allclose(v[box][cov], 100.0 / (sv * 256), rtol=1e-5)
    assert not u[box][~cov].any() and not v[box][~cov].any()


def test_positions_and_normals_interpolate_exactly_on_a_plane() -> None:
    pts, tris, uv = _grid(4, 50.0)
    maps = rasterize(pts, tris, uv, tris, 64, 0.001)
    cov = maps.coverage > 0
    jj, ii = np.nonzero(cov)
    expected_x = (ii + 0.5) / 64 * 50.0
    expected_y = (jj + 0.5) / 64 * 50.0
    np.testing.assert_allclose(maps.position[cov][:, 0], expected_x, atol=1e-4)
    np.testing.assert_allclose(maps.position[cov][:, 1], expected_y, atol=1e-4)
    np.testing.assert_allclose(maps.normal[cov], [[0, 0, 1]] * cov.sum(), atol=1e-6)
    assert cov.all()
    # as the seam layout reads them, texel by texel from the triangles
    position, normal = maps.texel_surface.at(np.flatnonzero(cov))
    np.testing.assert_allclose(position[:, 0], expected_x, atol=1e-4)
    np.testing.assert_allclose(position[:, 1], expected_y, atol=1e-4)
    np.testing.assert_allclose(normal, [[0, 0, 1]] * cov.sum(), atol=1e-6)


def test_the_texel_surface_of_a_cylinder_lies_on_its_chords() -> None:
    """TexelSurface.at on a half cylinder of radius 40 mm (u the angle over pi, v the
    height 0-60 mm, 32 x 8 cells): each texel centre's point lies on its cell's flat
    triangles, between the chord's distance from the axis, R cos(dtheta / 2), and R; at
    the angle and height its texel centre's u and v give (to within the triangles'
    sag); and its normal, interpolated from the vertex normals, is within a cell's angle
    of the radial direction there."""
    n_u, n_v, radius, height = 32, 8, 40.0, 60.0
    uv, tris = _cells(n_u, n_v)
    theta = np.pi * uv[:, 0]
    pts = np.stack([radius * np.cos(theta), radius * np.sin(theta), height * uv[:, 1]], 1)
    size = 128
    maps = rasterize(pts, tris, uv, tris, size, 0.001)
    texels = np.flatnonzero(maps.triangle.ravel() >= 0)
    position, normal = maps.texel_surface.at(texels)
    step = np.pi / n_u
    r_xy = np.hypot(position[:, 0], position[:, 1])
    assert r_xy.max() <= radius * (1 + 1e-6)
    assert r_xy.min() >= radius * np.cos(step / 2) * (1 - 1e-6)
    y, x = np.divmod(texels, size)
    angle = np.arctan2(position[:, 1], position[:, 0])
    np.testing.assert_allclose(angle, np.pi * (x + 0.5) / size, atol=step / 4)
    np.testing.assert_allclose(position[:, 2], height * (y + 0.5) / size, atol=1e-4)
    radial = np.stack([np.cos(angle), np.sin(angle), np.zeros_like(angle)], axis=1)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1), 1.0, atol=1e-6)
    assert np.arccos(np.clip((normal * radial).sum(axis=1), -1, 1)).max() < step


def test_region_weights_are_interpolated() -> None:
    pts, tris, uv = _grid(2, 10.0)
    w = np.stack([uv[:, 0], 1 - uv[:, 0]], axis=1)
    maps = rasterize(pts, tris, uv, tris, 32, 0.001, region_weights=w)
    assert maps.region_weights is not None
    assert maps.region_weights.dtype == np.float16  # half floats: within 2^-12 of 1
    np.testing.assert_allclose(maps.region_weights.sum(axis=2, dtype=np.float64), 1.0,
                               atol=2 * 2.0**-12)
    np.testing.assert_allclose(maps.region_weights[:, :, 0][0], (np.arange(32) + 0.5) / 32,
                               atol=2.0**-12)


def test_one_region_texels_keep_weights_of_exactly_one_and_zero() -> None:
    pts, tris, uv = _grid(2, 10.0)
    w = np.zeros((pts.shape[0], 3))
    w[:, 1] = 1.0
    maps = rasterize(pts, tris, uv, tris, 32, 0.001, region_weights=w)
    assert maps.region_weights is not None
    assert set(np.unique(maps.region_weights[..., 1]).tolist()) == {1.0}
    assert not maps.region_weights[..., [0, 2]].any()


def test_bad_inputs() -> None:
    pts, tris, uv = _grid(2, 10.0)
    with pytest.raises(InputError, match="texture size"):
        rasterize(pts, tris, uv, tris, 4, 0.001)
    bad = uv.copy()
    bad[0, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        rasterize(pts, tris, bad, tris, 32, 0.001)


def test_xatlas_unwrap_keeps_triangles_and_gives_finite_uvs() -> None:
    pts, tris, _ = _grid(10, 100.0)
    pts[:, 2] = 5.0 * np.sin(pts[:, 0] / 20.0)  # a gently curved sheet
    mesh = MeshData(pts, np.full(tris.shape[0], 3, np.int32), tris.reshape(-1), 0.001)
    layout = unwrap(mesh, resolution=256, timeout_s=60)
    assert layout.uv_indices.size == tris.size
    assert np.all((layout.uv >= 0) & (layout.uv <= 1))
    maps = rasterize(pts, triangulate(mesh), layout.uv, layout.uv_indices.reshape(-1, 3), 256,
                     0.001)
    cov = maps.coverage > 0
    # xatlas packs charts with uniform texel density: stretch varies little
    ratio = maps.mm_per_texel_u[cov] / np.median(maps.mm_per_texel_u[cov])
    assert np.percentile(np.abs(ratio - 1), 90) < 0.2


def test_unwrap_in_pieces_charts_no_triangle_across_them() -> None:
    # two halves of a curved sheet as pieces: xatlas charts them side by side; every UV
    # vertex belongs to one piece's triangles, and each maps back to its own vertex
    pts, tris, _ = _grid(10, 100.0)
    pts[:, 2] = 5.0 * np.sin(pts[:, 0] / 20.0)
    mesh = MeshData(pts, np.full(tris.shape[0], 3, np.int32), tris.reshape(-1), 0.001)
    pieces = (pts[tris].mean(axis=1)[:, 0] > 50.0).astype(np.int32)
    layout = unwrap(mesh, resolution=256, timeout_s=60, pieces=pieces)
    uv_tris = layout.uv_indices.reshape(-1, 3)
    owner = np.full(layout.uv.shape[0], -1)
    for piece in (0, 1):
        used = np.unique(uv_tris[pieces == piece])
        assert np.all(owner[used] == -1), "a UV vertex shared by both pieces"
        owner[used] = piece
    assert np.all(np.isfinite(layout.uv)) and np.all((layout.uv >= 0) & (layout.uv <= 1))
    # the texels cover the surface once: their areas add up to the sheet's (geometry)
    maps = rasterize(pts, triangulate(mesh), layout.uv, uv_tris, 256, 0.001)
    p = pts[tris]
    area_mm2 = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum()
    texels_mm2 = float((maps.mm_per_texel_u * maps.mm_per_texel_v)[maps.triangle >= 0].sum())
    assert abs(texels_mm2 / area_mm2 - 1) < 0.05
    whole = unwrap(mesh, resolution=256, timeout_s=60)
    assert layout.charts >= whole.charts >= 1
    with pytest.raises(InputError, match="one integer per triangle"):
        unwrap(mesh, pieces=pieces[:-1])


def test_unwrap_past_its_time_or_crashing_is_an_error(monkeypatch, tmp_path) -> None:
    import skinpipe.render.surface.unwrap as unwrap_module

    pts, tris, _ = _grid(10, 100.0)
    mesh = MeshData(pts, np.full(tris.shape[0], 3, np.int32), tris.reshape(-1), 0.001)
    with pytest.raises(SkinpipeError, match="did not finish in 0 s"):
        unwrap(mesh, timeout_s=0.01)
    crashing = tmp_path / "crash.py"
    crashing.write_text("import os, signal\nos.kill(os.getpid(), signal.SIGSEGV)\n")
    monkeypatch.setattr(unwrap_module, "_CHILD", crashing)
    with pytest.raises(SkinpipeError, match=r"xatlas crashed \(signal 11\)"):
        unwrap(mesh)


def test_unwrap_refuses_a_degenerate_mesh() -> None:
    pts = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])  # collinear: no area
    mesh = MeshData(pts, np.array([3], np.int32), np.array([0, 1, 2], np.int32), 0.001)
    with pytest.raises(InputError, match="no area"):
        unwrap(mesh)


def _same_maps(a: object, b: object) -> None:
    for name in ("triangle", "position", "mm_per_texel_u", "mm_per_texel_v", "region_weights"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None), name
        if x is not None:
            np.testing.assert_array_equal(x, y, err_msg=name)
    np.testing.assert_allclose(a.normal, b.normal, atol=2e-7)  # type: ignore[attr-defined]


def _same_surface_at_texels(maps: TextureMaps) -> None:
    """TexelSurface.at over every texel, covered or not, in a shuffled order: the maps'
    position bit for bit (products and sums, which OpenCL rounds as numpy does) and their
    normal within float32 rounding (OpenCL's square root and division may be off by an
    ulp or two), zero where no triangle covers the texel."""
    assert maps.position is not None and maps.normal is not None
    texels = np.random.default_rng(5).permutation(maps.triangle.size)
    position, normal = maps.texel_surface.at(texels)
    assert position.dtype == normal.dtype == np.float32
    np.testing.assert_array_equal(position, maps.position.reshape(-1, 3)[texels])
    np.testing.assert_allclose(normal, maps.normal.reshape(-1, 3)[texels], rtol=0, atol=4e-7)
    off = maps.triangle.reshape(-1)[texels] < 0
    assert not normal[off].any() and not position[off].any()


def test_device_rasteriser_equals_the_numpy_reference_on_awkward_triangles() -> None:
    # overlapping triangles (the highest index keeps a shared texel in both), a zero-area
    # one, one partly and one wholly outside the texture, texel centres on edges
    rng = np.random.default_rng(2)
    pts, tris, uv = _grid(6, 30.0)
    extra_uv = np.array([[0.1, 0.1], [0.6, 0.2], [0.3, 0.7],      # overlaps the grid
                         [0.2, 0.2], [0.4, 0.4], [0.6, 0.6],      # zero area
                         [-0.3, 0.5], [0.2, 0.4], [0.1, 1.4],     # partly outside
                         [1.2, 1.2], [1.5, 1.3], [1.3, 1.6]])     # wholly outside
    uv_all = np.vstack([uv, extra_uv])
    pts_all = np.vstack([pts, rng.uniform(0, 30, (extra_uv.shape[0], 3))])
    base = uv.shape[0]
    tris_all = np.vstack([tris, base + np.arange(extra_uv.shape[0]).reshape(-1, 3)]).astype(
        np.int32)
    w = rng.random((pts_all.shape[0], 3))
    for size in (8, 36, 127):  # 36: texel centres on the cells' diagonals (shared edges)
        args = (pts_all, tris_all, uv_all, tris_all, size, 0.001)
        device = rasterize(*args, region_weights=w)
        _same_maps(device, rasterize_reference(*args, region_weights=w))
        _same_maps(rasterize(*args), rasterize_reference(*args))
        _same_surface_at_texels(device)


def test_device_rasteriser_equals_the_numpy_reference_on_the_face_scan() -> None:
    # the real scan (holes, noise), decimated as the demo prepares it
    from skinpipe.usd.mesh import load_mesh, prepare_scan, pymeshlab_face_scan

    mesh = prepare_scan(load_mesh(pymeshlab_face_scan()), 20000)
    layout = unwrap(mesh, resolution=512, timeout_s=120)
    args = (mesh.points, triangulate(mesh), layout.uv, layout.uv_indices.reshape(-1, 3), 512,
            mesh.meters_per_unit)
    device = rasterize(*args)
    _same_maps(device, rasterize_reference(*args))
    _same_surface_at_texels(device)


def test_texel_areas_from_the_triangles_are_the_stretch_maps_product() -> None:
    """TextureMaps.texel_area_mm2 once the stretch maps are let go (each triangle's mm
    per texel, which the maps hold at its texels) is their product bit for bit, zero off
    the charts, for the device's maps and the numpy reference's; the maps let their
    surface go and keep or drop the stretch as asked."""
    pts, tris, uv = _grid(6, 30.0)
    for maps in (rasterize(pts, tris, uv * 0.8 + 0.1, tris, 64, 0.001),
                 rasterize_reference(pts, tris, uv * 0.8 + 0.1, tris, 64, 0.001)):
        want = maps.mm_per_texel_u * maps.mm_per_texel_v
        kept = maps.without_surface()
        assert kept.position is None and kept.mm_per_texel_u is maps.mm_per_texel_u
        let_go = maps.without_surface(keep_stretch=False)
        assert let_go.mm_per_texel_u is None and let_go.mm_per_texel_v is None
        assert let_go.coverage is maps.coverage
        for rows in (slice(None), slice(3, 40)):
            got = let_go.texel_area_mm2(rows)
            assert got.dtype == np.float32
            np.testing.assert_array_equal(got, want[rows])
        assert (let_go.texel_area_mm2()[maps.triangle < 0] == 0).all()
        # the stretch maps made from the triangles where read (the seam layout's boxes)
        u, v = maps.triangle_stretch()
        for box in ((slice(None), slice(None)), (slice(3, 40), slice(5, 61)),
                    (slice(0, 1), slice(63, 64))):
            for made, held in ((u, maps.mm_per_texel_u), (v, maps.mm_per_texel_v)):
                got = made[box]
                assert got.dtype == np.float32
                np.testing.assert_array_equal(got, held[box])


@pytest.mark.parametrize(("dtype", "off"), [(np.int32, -1), (np.float32, 0.0),
                                            (np.float64, np.nan)])
def test_at_texels_is_the_masked_gather(dtype: type, off: float) -> None:
    """at_texels (one gather through a table with ``off`` first) gives what numpy's
    masked gather gives, on a map and on a strided box of it, in the values' dtype; a
    map no triangle covers gives ``off`` even with no triangles at all."""
    rng = np.random.default_rng(7)
    triangle = rng.integers(-1, 50, size=(40, 60)).astype(np.int32)
    triangle[:, :10] = -1
    per_triangle = rng.random(50).astype(dtype) * 100
    for tri in (triangle, triangle[5:30:2, 3:50]):
        want = np.where(tri >= 0, per_triangle[np.maximum(tri, 0)], dtype(off))
        got = at_texels(tri, per_triangle, off)
        assert got.dtype == np.dtype(dtype) and got.shape == tri.shape
        np.testing.assert_array_equal(got, want)
    none = at_texels(np.full((3, 4), -1, np.int32), np.zeros(0, dtype), off)
    np.testing.assert_array_equal(none, np.full((3, 4), off, dtype))
