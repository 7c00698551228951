"""Render stage: analytic references (pencil light, energy, shadows, two regions), the
scene delegate's change tracking and caches, and bad assets."""

from __future__ import annotations

import json
import math
import struct
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from skinpipe.cli import main
from skinpipe.errors import InputError
from skinpipe.profile.models import fit_error_eq2c, sum_of_gaussians
from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.render.device import programs
from skinpipe.render.diffusion.diffuse import diffuse
from skinpipe.render.diffusion.layout import DiffusionLayout
from skinpipe.render.diffusion.terms import diffusion_terms, kept_diffusion_terms
from skinpipe.render.light.interleave import interleave_classes, texels_per_pixel
from skinpipe.render.light.irradiance import IrradianceResult, irradiance_texture
from skinpipe.render.light.raytrace import RayScene
from skinpipe.render.options import AOVS, DATA_AOVS, RenderOptions
from skinpipe.render.outputs import render_files
from skinpipe.render.renderer import Renderer
from skinpipe.render.scene import Camera, Light
from skinpipe.render.shading import normal_map
from skinpipe.render.surface.texture_maps import rasterize, texel_rows, texels_in_blocks
from skinpipe.render.surface.unwrap import triangulate, unwrap
from skinpipe.usd.io import open_stage_guarded
from skinpipe.usd.mesh import MeshData

from ..conftest import OPENCL_DEVICES
from ..png_chunks import png_chunks
from ..render_scenes import (
    deon_fit,
    distant_down,
    exact_fit,
    grid_patch,
    patch_asset,
    scene_over,
    top_camera,
)

# ------------------------------------------------------------------ analytic references


def _pencil_through_layout(uv_scale: tuple[float, float], offset: tuple[float, float],
                           size: int, fits: list, region_weights_fn=None,
                           lit_xy_mm: tuple[float, float] = (0.0, 0.0), patch_mm: float = 24.0):
    """Rasterise a flat patch with scaled UVs, light the texel under ``lit_xy_mm`` and
    diffuse; returns surface radii (mm) and the diffused profile per mm^2 there."""
    pts, tris, uv = grid_patch(24, patch_mm)
    uv = uv * uv_scale + offset
    rw = None if region_weights_fn is None else region_weights_fn(pts)
    maps = rasterize(pts, tris, uv, tris, size, 0.001, rw)
    cov = maps.coverage
    d = np.linalg.norm(maps.position[..., :2] - lit_xy_mm, axis=2) + (1 - cov) * 1e9
    j, i = np.unravel_index(np.argmin(d), d.shape)
    area = maps.mm_per_texel_u * maps.mm_per_texel_v
    e = np.zeros((size, size, 3), np.float32)
    e[j, i] = 1.0 / area[j, i]  # unit flux into one texel
    terms = diffusion_terms(fits, grid=0)
    out, _ = diffuse(e, maps.mm_per_texel_u, maps.mm_per_texel_v, cov, terms.variances_mm2,
                     terms.weights, maps.region_weights if rw is not None else None)
    r = np.linalg.norm(maps.position - maps.position[j, i], axis=2)
    sel = (cov > 0) & (r > 0.3) & (r < 3.5)
    order = np.argsort(r[sel])
    return r[sel][order], out[sel][order], area


@pytest.mark.parametrize(("uv_scale", "offset"), [
    ((0.5, 0.5), (0.25, 0.25)),   # 0.19 mm per texel: the sample face's density at 1024
    ((0.9, 0.9), (0.05, 0.05)),   # denser
    ((0.35, 0.7), (0.3, 0.15)),   # stretched: 0.27 x 0.13 mm per texel
])
def test_pencil_light_reproduces_the_profile_through_the_uv_layout(
        uv_scale: tuple[float, float], offset: tuple[float, float]) -> None:
    fit = deon_fit()
    r, got, _ = _pencil_through_layout(uv_scale, offset, 256, [fit])
    truth = sum_of_gaussians(fit.variances_mm2, fit.weights, r)
    assert fit_error_eq2c(r, got, truth).max() < 0.02


def test_energy_is_conserved_on_a_closed_mesh() -> None:
    import pymeshlab

    ms = pymeshlab.MeshSet()
    ms.create_sphere(radius=20.0, subdiv=4)
    m = ms.current_mesh()
    faces = np.asarray(m.face_matrix(), np.int32)
    mesh = MeshData(np.asarray(m.vertex_matrix(), np.float64), np.full(len(faces), 3, np.int32),
                    faces.reshape(-1), 0.001)
    layout = unwrap(mesh)
    maps = rasterize(mesh.points, triangulate(mesh), layout.uv,
                     layout.uv_indices.reshape(-1, 3), 512, 0.001)
    cov = maps.coverage
    # lit from +z (a hemisphere), with texture detail: flux crosses many chart borders
    lit = np.clip(maps.normal[..., 2], 0, None)
    rng = np.random.default_rng(0)
    e = (lit[..., None] * rng.uniform(0.5, 1.5, (512, 512, 3)) * cov[..., None]).astype(
        np.float32)
    fit = deon_fit()
    out, stats = diffuse(e, maps.mm_per_texel_u, maps.mm_per_texel_v, cov, fit.variances_mm2,
                         fit.weights)
    area = (maps.mm_per_texel_u * maps.mm_per_texel_v * cov)[..., None]
    ratio = (out * area).sum(axis=(0, 1)) / (e * area).sum(axis=(0, 1))
    np.testing.assert_allclose(ratio, 1.0, atol=5e-3)
    assert layout.charts > 10 and len(stats.levels) == fit.variances_mm2.size  # all blurred


def test_occluder_shadow_lands_where_geometry_says() -> None:
    pts, tris, _ = grid_patch(20, 100.0)
    occ_pts, occ_tris, _ = grid_patch(2, 20.0, z=10.0)
    rays = RayScene([(pts, tris), (occ_pts, occ_tris)])
    xs, ys = np.meshgrid(np.linspace(-45, 45, 91), np.linspace(-45, 45, 91))
    pos = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    nrm = np.tile([0.0, 0.0, 1.0], (pos.shape[0], 1))
    sun = Light("/Sun", "distant", np.array([2.0, 2.0, 2.0]), np.eye(4), angle_deg=0.0)
    res = irradiance_texture(pos, nrm, [sun], rays, samples=1)
    e = res.entering[:, 0]
    inside = (np.abs(pos[:, 0]) < 9.5) & (np.abs(pos[:, 1]) < 9.5)
    outside = (np.abs(pos[:, 0]) > 10.5) | (np.abs(pos[:, 1]) > 10.5)
    assert np.all(e[inside] == 0)
    # light straight down: the measured albedo's own incidence, nothing more is lost
    expected = 2.0
    np.testing.assert_allclose(e[outside], expected, rtol=1e-5)
    # a light 45 degrees off moves the shadow by the occluder's height (10 mm) along x
    tilt = np.eye(4)
    c = math.sqrt(0.5)
    tilt[2, :3] = [c, 0.0, c]  # local +Z -> emits towards -(c, 0, c)
    res = irradiance_texture(pos, nrm, [Light("/Sun", "distant", np.ones(3), tilt, 0.0)], rays, 1)
    moved = (np.abs(pos[:, 0] + 10) < 9.5) & (np.abs(pos[:, 1]) < 9.5)
    assert np.all(res.entering[moved, 0] == 0)


def test_embree_agrees_with_brute_force_on_the_cleaned_scan() -> None:
    """Embree drops bad triangles silently (light leaks); on the cleaned scan every
    shadow ray must agree with a brute-force ray/triangle test."""
    from skinpipe.usd.mesh import load_mesh, prepare_scan, pymeshlab_face_scan

    mesh = prepare_scan(load_mesh(pymeshlab_face_scan()), 20000)
    tris = triangulate(mesh)
    rays = RayScene([(mesh.points, tris)])
    rng = np.random.default_rng(3)
    centre = mesh.points.mean(axis=0)
    origins = centre + rng.normal(0, 40, (200, 3)) + [0, 0, 150]
    dirs = centre + rng.normal(0, 30, (200, 3)) - origins
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    got = rays.occluded(origins, dirs)
    p = mesh.points[tris]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    expected = []
    for o, d in zip(origins, dirs, strict=True):  # Moller-Trumbore, all triangles at once
        h = np.cross(d, e2)
        a = (e1 * h).sum(axis=1)
        ok = np.abs(a) > 1e-12
        f = np.where(ok, 1 / np.where(ok, a, 1), 0)
        s = o - p[:, 0]
        u = f * (s * h).sum(axis=1)
        q = np.cross(s, e1)
        v = f * (q @ d)
        t = f * (e2 * q).sum(axis=1)
        expected.append(bool(np.any(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6))))
    expected = np.array(expected)
    assert 20 < expected.sum() < 190  # the rays test both hits and misses
    assert np.mean(got == expected) >= 0.99  # grazing edge cases may differ


def test_two_regions_each_match_their_profile_and_blend_at_the_border() -> None:
    a = exact_fit("a", DEON_2007_SKIN.variances_mm2[:4], DEON_2007_SKIN.weights[:4])
    b = exact_fit("b", DEON_2007_SKIN.variances_mm2[:4] * 3.0, DEON_2007_SKIN.weights[:4])

    def weights(pts: np.ndarray) -> np.ndarray:
        t = np.clip((pts[:, 0] + 1.0) / 2.0, 0, 1)  # a 2 mm ramp at x = 0
        return np.stack([1 - t, t], axis=1)

    for fit, x in ((a, -10.0), (b, 10.0)):
        r, got, _ = _pencil_through_layout((0.9, 0.9), (0.05, 0.05), 256, [a, b], weights,
                                           lit_xy_mm=(x, 0.0), patch_mm=40.0)
        truth = sum_of_gaussians(fit.variances_mm2, fit.weights, r)
        assert fit_error_eq2c(r, got, truth).max() < 0.02, fit.name
    # across the border: uniform light stays uniform (each profile integrates to 1) and
    # a light/dark edge along the border leaves no step larger than its neighbours'
    pts, tris, uv = grid_patch(24, 40.0)
    maps = rasterize(pts, tris, uv * 0.9 + 0.05, tris, 256, 0.001, weights(pts))
    cov = maps.coverage
    terms = diffusion_terms([a, b])
    flat = (np.ones((256, 256, 3)) * cov[..., None]).astype(np.float32)
    out, _ = diffuse(flat, maps.mm_per_texel_u, maps.mm_per_texel_v, cov, terms.variances_mm2,
                     terms.weights, maps.region_weights)
    inner = (cov > 0) & (np.abs(maps.position[..., 1]) < 12) & (np.abs(maps.position[..., 0]) < 12)
    np.testing.assert_allclose(out[inner], 1.0, rtol=1e-4)
    row = np.argmin(np.where(cov[:, 128] > 0, np.abs(maps.position[:, 128, 1]), np.inf))
    w_row = maps.region_weights[row, :, 1][cov[row] > 0]
    assert np.all(np.diff(w_row) >= -1e-6) and np.abs(np.diff(w_row)).max() < 0.1


def test_shared_variance_grid_reports_its_error() -> None:
    fits = [deon_fit("a"), deon_fit("b", 2.0)]
    exact = diffusion_terms(fits, grid=0)
    assert exact.variances_mm2.size == 12 and max(exact.error.values()) == 0
    shared = diffusion_terms(fits, grid=10)
    assert shared.variances_mm2.size <= 10
    assert 0 < max(shared.error.values()) < 0.05
    np.testing.assert_allclose(shared.weights.sum(axis=1), 1.0, rtol=1e-9)
    same = diffusion_terms([deon_fit("a"), deon_fit("b")])
    assert same.variances_mm2.size == 6 and "merged" in same.notes[0]
    with pytest.raises(InputError, match="single profile"):
        diffusion_terms(fits, single="nose")


def test_kept_diffusion_terms_are_the_terms_bit_for_bit(tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch
                                                       ) -> None:
    """The blur schedule, made (scipy's NNLS) and then read back from skinpipe's cache
    folder, is diffusion_terms' own, bit for bit; other inputs are another file; a kept
    file that does not read back, or whose weights do not fit the fits, is made again;
    a cache folder that cannot be written keeps nothing."""
    from skinpipe.render import cache as kept_module
    from skinpipe.render.cache import write_json_entry
    from skinpipe.render.diffusion import terms as terms_module

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    fits = [deon_fit("a"), deon_fit("b", 2.0)]
    cases = [dict(grid=10, floor_mm2=1e-3), dict(grid=10, floor_mm2=2e-3),
             dict(grid=0), dict(grid=6, single="b")]
    wants = [diffusion_terms(fits, **case) for case in cases]

    def same(got: Any, want: Any) -> None:
        assert got.variances_mm2.tobytes() == want.variances_mm2.tobytes()
        assert got.weights.tobytes() == want.weights.tobytes()
        assert got.error == want.error and got.notes == want.notes

    for case, want in zip(cases, wants, strict=True):
        same(kept_diffusion_terms(fits, **case), want)  # made and kept
    folder = tmp_path / "cache" / "skinpipe" / "diffusion-terms"
    assert len(list(folder.glob("terms-*.json"))) == len(cases)

    made: list[Any] = []

    def counted(path: Path, key: Any, doc: Any) -> None:
        made.append(path)

    monkeypatch.setattr(kept_module, "write_json_entry", counted)
    for case, want in zip(cases, wants, strict=True):  # read back: nothing made
        same(kept_diffusion_terms(fits, **case), want)
    assert made == []
    original = terms_module.diffusion_terms

    def edited(*args: Any, **kwargs: Any) -> Any:  # other source: terms made again
        return original(*args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(terms_module, "diffusion_terms", edited)
        same(kept_diffusion_terms(fits, **cases[0]), wants[0])
    assert len(made) == 1
    monkeypatch.undo()
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    for damage in ("{", "weights"):
        for kept in folder.glob("terms-*.json"):
            if damage == "weights":  # one region's weights fewer than the fits
                entry = json.loads(kept.read_text())
                doc = entry["payload"]
                doc["weights"] = doc["weights"][:1]
                write_json_entry(kept, entry["key"], doc)  # its checksum holds
            else:
                kept.write_text(damage)
        for case, want in zip(cases, wants, strict=True):
            same(kept_diffusion_terms(fits, **case), want)  # made again
    (tmp_path / "ro").mkdir()
    (tmp_path / "ro" / "skinpipe").write_text("a file where the folder would go")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "ro"))
    same(kept_diffusion_terms(fits, **cases[0]), wants[0])


@pytest.mark.parametrize("shape", [(4, 4), (3, 5), (1, 7), (7, 1), (9, 10)])
@pytest.mark.parametrize("period", [2, 4, 8])
def test_interleave_classes_are_the_texels_rows_and_columns_modulo_the_period(
        shape: tuple[int, int], period: int) -> None:
    y, x = np.indices(shape)
    classes = interleave_classes(shape, period)
    assert classes.dtype == np.uint8
    np.testing.assert_array_equal(classes, (period * (y % period) + x % period).ravel())


def test_texels_per_pixel_is_the_pixels_footprint_over_the_texels() -> None:
    """A 40 mm square patch (UVs over [0, 1]) on a 128 texture: texels 0.3125 mm. A
    camera 100 mm above it (focal length 50, aperture 45) sees 90 mm across 48 pixels,
    1.875 mm each: 6 texels a pixel; an orthographic view 150 mm wide, 3.125 mm: 10; a
    patch behind the camera or without area: 0 (unknown)."""
    pts, tris, uv = grid_patch(4, 40.0)
    up = Camera("/Cam", np.array([0.0, 0.0, 100.0]), np.eye(3), 50.0, 45.0, 45.0)
    assert texels_per_pixel(pts, tris, uv, tris, 128, up, 48) == pytest.approx(6.0)
    assert texels_per_pixel(pts, tris, uv, tris, 256, up, 96) == pytest.approx(6.0)
    ortho = Camera("/Cam", np.array([0.0, 0.0, 100.0]), np.eye(3), 50.0, 150.0, 150.0,
                   "orthographic")
    assert texels_per_pixel(pts, tris, uv, tris, 128, ortho, 48) == pytest.approx(10.0)
    below = Camera("/Cam", np.array([0.0, 0.0, -100.0]), np.eye(3), 50.0, 45.0, 45.0)
    assert texels_per_pixel(pts, tris, uv, tris, 128, below, 48) == 0.0
    assert texels_per_pixel(pts, tris, uv * 0.0, tris, 128, up, 48) == 0.0


def test_the_render_takes_the_interleaving_period_of_its_texels_per_pixel(
        lit_patch: Path) -> None:
    """The lit patch at 6 texels a pixel: period 4 at 16 light samples and at 64 (8
    needs 8 texels a pixel: 12 at texture 256 takes it), 2 at one sample, the option's
    where it is set; render.json's measures say which, and the period is part of the
    irradiance's key."""
    from dataclasses import replace

    stage = open_stage_guarded(lit_patch)
    for options, period in ((replace(SMALL, light_samples=16), 4), (SMALL, 2),
                            (replace(SMALL, light_samples=64), 4),
                            (replace(SMALL, light_samples=64, texture_size=256), 8),
                            (replace(SMALL, light_samples=16, interleave_period=2), 2)):
        renderer = Renderer(stage, options)
        _, log = renderer.render()
        assert log.measures["irradiance"]["interleave_period"] == period
        assert log.measures["irradiance"]["texels_per_pixel"] == pytest.approx(
            6.0 * options.texture_size / 128, rel=1e-3)
        if period != 2:  # another period, another irradiance
            key = renderer.textures[0].keys["irradiance"]
            renderer.options = replace(options, interleave_period=2)
            assert renderer.skin_textures(log, renderer.delegate.sync(None),
                                      renderer.textures[0].mesh).keys["irradiance"] != key
        renderer.close()
    # a period asked for whose classes the samples cannot fill: the largest that they
    # can, and a note (16 samples: 4, not 8, which would trace every sample)
    renderer = Renderer(stage, replace(SMALL, light_samples=16, interleave_period=8))
    _, log = renderer.render()
    renderer.close()
    assert log.measures["irradiance"]["interleave_period"] == 4
    assert any("interleave period 8: 16 light samples" in s for s in log.skipped)
    with pytest.raises(InputError, match="interleave period"):
        replace(SMALL, interleave_period=3)


# ----------------------------------------------------------------- scenes through USD


SMALL = RenderOptions(resolution=(48, 48), texture_size=128, light_samples=1)


def test_render_of_a_lit_patch_is_albedo_times_irradiance(lit_patch: Path) -> None:
    renderer = Renderer(open_stage_guarded(lit_patch), SMALL)
    images, log = renderer.render()
    renderer.close()
    alpha = images["beauty"][..., 3]
    assert alpha[24, 24] == 1 and alpha[0, 0] == 0  # the patch fills the centre only
    # uniform light on a flat patch: diffusion leaves it uniform; radiance = a E / pi.
    # Light enters and leaves at normal incidence, where the albedo was measured: it is
    # not attenuated a second time (the Fresnel share is relative to normal incidence)
    albedo = np.array([0.62, 0.42, 0.33])  # the authored constant diffuseColor
    np.testing.assert_allclose(images["diffuse"][24, 24], albedo * 2.0 / math.pi,
                               rtol=2e-3)
    assert images["specular"][24, 24].max() > 0  # the sun reflects straight up
    assert "unwrap" not in log.seconds  # the patch has usable st


@pytest.mark.skipif(len(OPENCL_DEVICES) < 2, reason="one OpenCL runtime here")
def test_each_renderer_runs_on_its_own_device(lit_patch: Path,
                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Two renderers in one process asking for two devices: each one's kernels run on
    its own (the device is handed down, not a process-wide choice that the last one
    made wins), and the images agree within the runtimes' rounding."""
    first, second = (c.runtime for c in OPENCL_DEVICES[:2])
    renderers = [Renderer(open_stage_guarded(lit_patch), replace(SMALL, device=spec))
                 for spec in (first, second)]
    call = programs.Kernel.__call__
    seen: list[str] = []

    def recorded(self: Any, queue: Any, *args: Any, **kwargs: Any) -> Any:
        seen.append(queue.device.platform.name)
        return call(self, queue, *args, **kwargs)

    monkeypatch.setattr(programs.Kernel, "__call__", recorded)
    images = []
    for renderer in renderers:
        seen.clear()
        images.append(renderer.render()[0]["beauty"])
        renderer.close()
        assert seen and set(seen) == {renderer.device.cl_device.platform.name}, set(seen)
    np.testing.assert_allclose(images[0], images[1], atol=1e-3)


def test_camera_change_reuses_texture_space_work(lit_patch: Path) -> None:
    from pxr import Gf, UsdGeom

    stage = open_stage_guarded(lit_patch)
    renderer = Renderer(stage, SMALL)
    first, _ = renderer.render()
    again, log = renderer.render()  # the same camera: its rays and hits too
    assert "camera_hits" in log.cached
    for aov, image in first.items():
        np.testing.assert_array_equal(again[aov], image, err_msg=aov)
    cam = UsdGeom.Xformable(stage.GetPrimAtPath("/Cam"))
    cam.GetOrderedXformOps()[0].Set(Gf.Vec3d(5, 0, 90))  # a USD edit: a notice marks it
    moved, log = renderer.render()
    assert {"texture_maps", "irradiance", "diffusion"} <= set(log.cached)
    assert "camera_hits" not in log.cached
    assert not np.array_equal(moved["beauty"], first["beauty"])
    stage.GetPrimAtPath("/Sun").GetAttribute("inputs:intensity").Set(4.0)
    _, log = renderer.render()
    assert "irradiance" in log.seconds and "texture_maps" in log.cached
    renderer.close()


def test_an_albedo_split_of_a_half_makes_no_albedo_map_and_renders_the_same(
        lit_patch: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A textured albedo with the default split (0.5, a square root before the blur and
    after): its weights and the albedo AOV come from the albedo's own image, no map of
    it is made, and every image is the one a render that makes the map and weighs with
    it gives, bit for bit (a map is made for a split whose powers the device does not
    take as numpy does)."""
    from dataclasses import replace

    import skinpipe.render.renderer as renderer_module

    rng = np.random.default_rng(4)
    image = (rng.random((19, 27, 3)) * 0.9 + 0.1).astype(np.float32)
    image[3, 4] = -0.2  # clipped at 0, on both paths
    monkeypatch.setattr(renderer_module, "albedo_image",
                        lambda mesh, working: (image, "a test image"))
    options = replace(SMALL, aovs=AOVS)
    renderer = Renderer(open_stage_guarded(lit_patch), options)
    got, log = renderer.render()
    renderer.close()
    assert renderer.textures[0].albedo is None and "albedo_map" not in log.seconds
    assert log.measures["albedo_source"] == "a test image"
    monkeypatch.setattr(renderer_module, "EXACT_POWERS", {})  # the map and numpy's weights
    renderer = Renderer(open_stage_guarded(lit_patch), options)
    want, log = renderer.render()
    renderer.close()
    assert "albedo_map" in log.seconds
    assert got.keys() == want.keys()
    for aov, values in want.items():
        np.testing.assert_array_equal(got[aov], values, err_msg=aov)
    assert got["albedo"].max() > 0.5  # the texture, not a constant


def test_an_interleaved_render_does_not_sum_the_irradiance_it_replaces(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Under a sampled (5 degree) sun, the interleaved render's irradiance is made from
    the filtered visibility (entering_with) and never from the rays' own sums, which it
    would replace (IrradianceResult.entering is not read); full sampling reads them."""
    from dataclasses import replace

    asset = patch_asset(tmp_path / "asset", [deon_fit()])
    scene = scene_over(asset, tmp_path / "scene.usda", lambda stage: (
        top_camera(stage), distant_down(stage, intensity=2.0, angle=5.0)))
    made = IrradianceResult.entering.func  # type: ignore[attr-defined]
    read: list[str] = []

    def entering(self: IrradianceResult) -> np.ndarray:
        read.append("entering")
        return made(self)

    monkeypatch.setattr(IrradianceResult, "entering", property(entering))
    for sampling, want in (("interleaved", []), ("full", ["entering"])):
        read.clear()
        renderer = Renderer(open_stage_guarded(scene),
                            replace(SMALL, light_samples=16, shadow_sampling=sampling))
        _, log = renderer.render()
        renderer.close()
        assert read == want, sampling
        assert log.measures["irradiance"]["rays"] > 0


def test_a_render_without_scattering_keeps_the_seam_layout(lit_patch: Path) -> None:
    """The demo's order: with scattering, without (figure 7's left half), then other
    terms again. The layout depends on the UV layout and geometry alone, so the third
    render takes it from the cache (the texture-only render used to replace it: 6-8 s
    of the demo's comparisons)."""
    from dataclasses import replace

    renderer = Renderer(open_stage_guarded(lit_patch), SMALL)
    _, first = renderer.render()
    assert "diffusion_layout" in first.seconds
    renderer.options = replace(SMALL, scattering=False)
    renderer.render()
    renderer.options = replace(SMALL, albedo_split=0.3)  # new diffusion, same layout
    _, third = renderer.render()
    renderer.close()
    assert "diffusion_layout" in third.cached and "diffusion" in third.seconds


def test_a_last_frame_lets_the_surface_maps_go_and_renders_the_same(lit_patch: Path
                                                                     ) -> None:
    """A render's last frame lets the position and normal maps, and its seam layout's
    surface, go once the irradiance and the layout are made, and the irradiance and
    visibility maps once the diffusion has read them (the shading's lookups taken
    before): the same images bit for bit as a frame that keeps them; a later frame of
    the same renderer makes them again (the same images), and the let-go layout makes
    no tiles without its surface."""
    from dataclasses import replace

    kept = Renderer(open_stage_guarded(lit_patch), SMALL)
    want, _ = kept.render()
    assert kept.textures[0].maps.position is not None
    assert kept.textures[0].irradiance_filled is not None and kept.textures[0].at_hits is None
    kept.close()
    renderer = Renderer(open_stage_guarded(lit_patch), SMALL)
    renderer.last_frame = True
    layouts: list[DiffusionLayout] = []
    release = DiffusionLayout.release_surface
    beside, albedo = Renderer._layout_beside, Renderer.albedo
    at_albedo: list[bool] = []

    def spy(layout: DiffusionLayout) -> None:
        layouts.append(layout)
        release(layout)

    def layout_done_first(self: Renderer, *args: Any) -> Any:
        made = beside(self, *args)
        if made is not None:
            made.result()  # made before the irradiance takes the texels' rows
        return made

    def albedo_after_irradiance(self: Renderer, log: Any, scene: Any, tex: Any) -> None:
        at_albedo.append(tex.maps.position is None and tex.maps.normal is None)
        albedo(self, log, scene, tex)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(DiffusionLayout, "release_surface", spy)
        mp.setattr(Renderer, "_layout_beside", layout_done_first)
        mp.setattr(Renderer, "albedo", albedo_after_irradiance)
        got, _ = renderer.render()
    assert at_albedo == [True]  # let go by the irradiance, not at the diffusion
    maps = renderer.textures[0].maps
    assert maps.position is None and maps.normal is None
    assert maps.mm_per_texel_u is None and maps.mm_per_texel_v is None  # recursive blur
    # the albedo map went after its weight before the blur and the shading's lookups: the
    # weight after it was made from the albedo's own image
    assert renderer.textures[0].albedo is None
    assert renderer.textures[0].albedo_image is not None
    assert "albedo" in renderer.textures[0].at_hits["center"]
    assert renderer.textures[0].irradiance_filled is None and not renderer.textures[0].visibility
    assert renderer.textures[0].at_hits is not None
    with pytest.raises(RuntimeError, match="let go"):
        _ = maps.surface
    with pytest.raises(RuntimeError, match="let go"):
        layouts[0].grid(2, 99)  # tiles it never made
    for aov, image in want.items():
        np.testing.assert_array_equal(got[aov], image, err_msg=aov)
    renderer.last_frame = False
    again, log = renderer.render()
    assert "texture_maps" in log.seconds and "irradiance" in log.seconds
    assert "diffusion" in log.cached and renderer.textures[0].irradiance_filled is not None
    assert renderer.textures[0].maps.position is not None
    for aov, image in want.items():
        np.testing.assert_array_equal(again[aov], image, err_msg=aov)
    renderer.options = replace(SMALL, albedo_split=0.3)  # new terms: the layout again
    _, log = renderer.render()
    renderer.close()
    assert "diffusion_layout" in log.seconds


def test_a_normal_map_made_from_its_covered_rows_is_the_rasterized_one(lit_patch: Path
                                                                        ) -> None:
    """:func:`normal_map` (the filter's, once the maps let theirs go) from the covered
    texels' rows is the rasterizer's normal map bit for bit, zeros off the charts
    included."""
    renderer = Renderer(open_stage_guarded(lit_patch), SMALL)
    renderer.render()
    maps = renderer.textures[0].maps
    renderer.close()
    texel = texels_in_blocks(maps.triangle >= 0)
    made = normal_map(texel_rows(maps.normal, texel), texel, maps.triangle.shape)
    assert made.dtype == maps.normal.dtype
    np.testing.assert_array_equal(made, maps.normal)


def test_the_layout_beside_the_irradiance_reports_errors_and_ends_with_the_frame(
        lit_patch: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The seam layout runs on a thread beside the irradiance: an error of either side
    reaches the caller as itself, and no layout thread outlives the frame (one still
    working when the irradiance failed would hold the process at exit)."""
    import threading
    import time

    import skinpipe.render.renderer as renderer_module

    def slow_layout(*args: object, **kwargs: object) -> object:
        time.sleep(0.5)  # still working when the irradiance fails
        raise InputError("chart layout: bad UVs")

    monkeypatch.setattr(renderer_module, "chart_layout", slow_layout)
    renderer = Renderer(open_stage_guarded(lit_patch), SMALL)
    with pytest.raises(InputError, match="bad UVs"):
        renderer.render()

    def no_light(*args: object, **kwargs: object) -> object:
        raise InputError("irradiance: no light")

    monkeypatch.setattr(renderer_module, "irradiance_texture", no_light)
    renderer.clear_cache()
    with pytest.raises(InputError, match="no light"):
        renderer.render()
    renderer.close()
    layout_threads = [t for t in threading.enumerate() if t.name.startswith("skinpipe-layout")]
    for t in layout_threads:
        t.join(0.2)  # a thread whose task is done ends at once; a working one would not
    assert not [t for t in layout_threads if t.is_alive()]


def test_each_aov_asked_alone_equals_it_among_all(lit_patch: Path) -> None:
    """Shading makes only the AOVs asked for; each is the same, bit for bit, as when
    every AOV is asked for (and beauty is still diffuse plus specular inside the patch)."""
    from dataclasses import replace

    renderer = Renderer(open_stage_guarded(lit_patch), replace(SMALL, aovs=AOVS + DATA_AOVS))
    every, _ = renderer.render()
    for aov in AOVS + DATA_AOVS:
        renderer.options = replace(SMALL, aovs=(aov,))
        alone, _ = renderer.render()
        assert set(alone) == {aov}
        np.testing.assert_array_equal(alone[aov], every[aov], err_msg=aov)
    renderer.close()
    assert every["region"].max() >= 0 and every["albedo"].max() > 0
    inside = every["beauty"][..., 3] == 1
    np.testing.assert_allclose(every["beauty"][inside, :3],
                               (every["diffuse"] + every["specular"])[inside], rtol=1e-6)


def test_turntable_frames_compute_diffusion_once(tmp_path: Path) -> None:
    from pxr import Gf, UsdGeom

    asset = patch_asset(tmp_path / "asset", [deon_fit()])

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage)
        op = UsdGeom.Xformable(stage.GetPrimAtPath("/Cam")).GetOrderedXformOps()[0]
        for f in (1, 2, 3):
            op.Set(Gf.Vec3d(f, 0, 100), f)

    scene = scene_over(asset, tmp_path / "scene.usda", build)
    doc = render_files(scene, tmp_path / "out", SMALL, frames=(1, 3))
    assert [f["frame"] for f in doc["frames"]] == [1, 2, 3]
    for frame in doc["frames"][1:]:
        assert "diffusion" in frame["cached"] and "diffusion" not in frame["tasks"]
    assert (tmp_path / "out" / "scene.0003.exr").is_file()
    saved = json.loads((tmp_path / "out" / "render.json").read_text())
    assert saved["frames"][0]["measures"]["diffusion"]["blur_passes"] > 0
    # which device ran, what was built and which kernels ran (all three frames)
    cl_doc = saved["opencl"]
    assert cl_doc["device"] and cl_doc["tried"][cl_doc["device"]] == "passed"
    assert cl_doc["build_seconds"] >= 0 and cl_doc["programs_built"] >= 0
    assert cl_doc["kernel_launches"].get("claim_texels", 0) >= 1
    assert cl_doc["blur_switch"]["max_radius"] >= 0


def test_output_has_aov_layers_and_colour_space(lit_patch: Path, tmp_path: Path) -> None:
    import OpenImageIO as oiio

    out = tmp_path / "out"
    assert main(["render", str(lit_patch), "--resolution", "32x24", "--texture-size", "128",
                 "--aovs", "beauty,diffuse", "--light-samples", "1", "-o", str(out)]) == 0
    spec = oiio.ImageInput.open(str(out / "scene.exr")).spec()
    assert (spec.width, spec.height) == (32, 24)
    assert spec.getattribute("oiio:ColorSpace") == "lin_ap1_scene"
    assert set(spec.channelnames) == {"R", "G", "B", "A", "diffuse.R", "diffuse.G",
                                      "diffuse.B"}
    doc = json.loads((out / "render.json").read_text())
    assert any("AOVs not asked for" in s for s in doc["frames"][0]["skipped"])
    assert (out / "scene.png").is_file()
    # OpenEXR: without chromaticities a reader takes Rec.709; these are ACEScg's (AP1,
    # ACES white), compared with colour-science's definition of the space
    import colour

    acescg = colour.models.RGB_COLOURSPACE_ACESCG
    want = [*np.asarray(acescg.primaries).ravel(), *acescg.whitepoint]
    np.testing.assert_allclose(spec.getattribute("chromaticities"), want, atol=1e-4)
    # the display PNG says it is sRGB: an sRGB chunk before the pixels (ISO/IEC 15948
    # 11.3.3.5; rendering intent 0-3), with the gAMA and cHRM a reader without colour
    # management falls back to (1/2.2 as 45455; Rec.709 primaries, D65)
    chunks = png_chunks(out / "scene.png")
    kinds = [k for k, _ in chunks]
    assert "sRGB" in kinds and kinds.index("sRGB") < kinds.index("IDAT"), kinds
    assert dict(chunks)["sRGB"] in (b"\x00", b"\x01", b"\x02", b"\x03")
    assert struct.unpack(">I", dict(chunks)["gAMA"]) == (45455,)
    np.testing.assert_allclose(np.array(struct.unpack(">8I", dict(chunks)["cHRM"])) / 1e5,
                               [0.3127, 0.329, 0.64, 0.33, 0.3, 0.6, 0.15, 0.06], atol=1e-4)
    png = oiio.ImageInput.open(str(out / "scene.png"))
    assert png.spec().getattribute("oiio:ColorSpace").startswith("srgb")
    png.close()
    # half float on request, the same image to half's precision
    half = tmp_path / "half"
    assert main(["render", str(lit_patch), "--resolution", "32x24", "--texture-size", "128",
                 "--aovs", "beauty,diffuse", "--light-samples", "1", "--half-float", "-o",
                 str(half)]) == 0
    h = oiio.ImageInput.open(str(half / "scene.exr"))
    assert h.spec().format == "half"
    f = oiio.ImageInput.open(str(out / "scene.exr"))
    np.testing.assert_allclose(h.read_image("float"), f.read_image("float"), rtol=1e-3,
                               atol=1e-4)
    h.close()
    f.close()


def test_missing_uvs_are_unwrapped_and_written_back(tmp_path: Path) -> None:
    from pxr import Usd, UsdGeom

    asset = patch_asset(tmp_path / "asset", [deon_fit()], n=8, with_uv=False)

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage)

    scene = scene_over(asset, tmp_path / "scene.usda", build)
    doc = render_files(scene, tmp_path / "out", SMALL)
    assert doc["frames"][0]["measures"]["unwrap"]["written_to"].endswith("geo.usdc")
    geo = Usd.Stage.Open(str(tmp_path / "asset" / "geo.usdc"))
    st = UsdGeom.PrimvarsAPI(geo.GetPrimAtPath("/Patch/Geom/Mesh")).GetPrimvar("st")
    assert st.GetInterpolation() == "faceVarying" and st.IsIndexed()
    doc = render_files(scene, tmp_path / "out2", SMALL)  # the next run reuses them
    assert "unwrap" not in doc["frames"][0]["measures"]


# ----------------------------------------------------------------------- bad assets


def _bad(tmp_path: Path, edit) -> Path:
    asset = patch_asset(tmp_path / "asset", [deon_fit()], n=4)

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage)
        edit(stage)

    return scene_over(asset, tmp_path / "scene.usda", build)


def _points(stage, fn) -> None:
    from pxr import UsdGeom, Vt

    mesh = UsdGeom.Mesh(stage.OverridePrim("/Patch/Geom/Mesh"))
    pts = grid_patch(4, 40.0)[0]  # what patch_asset(n=4) authored
    mesh.CreatePointsAttr().Set(Vt.Vec3fArray.FromNumpy(fn(pts).astype(np.float32)))


@pytest.mark.parametrize(("case", "message"), [
    ("no_lights", "no UsdLux light"),
    ("no_mesh", "no visible mesh"),
    ("nan_points", "non-finite point"),
    ("zero_area", "no area"),
    ("missing_texture", "not found"),
    ("no_camera", "no UsdGeomCamera"),
])
def test_bad_assets_give_clear_errors(tmp_path: Path, case: str, message: str,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    from pxr import Sdf, UsdGeom

    def edit(stage) -> None:
        if case == "no_lights":
            stage.RemovePrim("/Sun")
        elif case == "no_camera":
            stage.RemovePrim("/Cam")
        elif case == "no_mesh":
            UsdGeom.Imageable(stage.OverridePrim("/Patch/Geom/Mesh")).CreateVisibilityAttr(
                "invisible")
        elif case == "nan_points":
            _points(stage, lambda p: np.where(np.arange(len(p))[:, None] == 3, np.nan, p))
        elif case == "zero_area":
            _points(stage, lambda p: p * [1.0, 0.0, 0.0])
            UsdGeom.PrimvarsAPI(stage.OverridePrim("/Patch/Geom/Mesh")).CreatePrimvar(
                "st", Sdf.ValueTypeNames.TexCoord2fArray, "vertex").Set([(0.0, 0.0)] * 25)
        elif case == "missing_texture":
            from pxr import UsdShade

            mat = "/Patch/Looks/SkinMaterial"
            tex = UsdShade.Shader.Define(stage, f"{mat}/Tex")
            tex.CreateIdAttr("UsdUVTexture")
            tex.CreateInput("file", Sdf.ValueTypeNames.Asset).Set("./nowhere.exr")
            surf = UsdShade.Shader(stage.OverridePrim(f"{mat}/PreviewSurface"))
            surf.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).ConnectToSource(
                tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))

    scene = _bad(tmp_path, edit)
    code = main(["render", str(scene), "--resolution", "16x16", "--texture-size", "64",
                 "--light-samples", "1", "-o", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert code == 2, err
    assert message in err
    assert not (tmp_path / "out" / "scene.exr").exists()


def _ortho_scene(tmp_path: Path, height: float, asset: Path) -> Path:
    def build(stage) -> None:
        from pxr import Gf, UsdGeom

        cam = UsdGeom.Camera.Define(stage, "/Cam")
        cam.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
        cam.CreateHorizontalApertureAttr(1500.0)  # tenths of a mm: a 150 mm wide view
        cam.CreateVerticalApertureAttr(1500.0)
        UsdGeom.Xformable(cam).AddTranslateOp().Set(Gf.Vec3d(0, 0, height))
        distant_down(stage, intensity=2.0)

    return scene_over(asset, tmp_path / f"ortho_{height:g}.usda", build)


def test_a_perspective_cameras_rays_share_one_origin() -> None:
    """A pinhole camera's rays start at its position, one read-only point for all of
    them (no copy a ray); an orthographic camera's start on its film plane, each its own;
    the directions are unit vectors through the pixel centres either way."""
    persp = Camera("/Cam", np.array([1.0, 2.0, 100.0]), np.eye(3), 50.0, 36.0, 24.0)
    origins, dirs = persp.rays(6, 4)
    assert origins.shape == (24, 3) and origins.strides[0] == 0
    assert not origins.flags.writeable
    np.testing.assert_array_equal(origins, np.broadcast_to(persp.position, (24, 3)))
    np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, rtol=1e-12)
    # the top-left pixel centre's ray: x = (0.5 / 6 - 0.5) * 36 mm, y = (0.5 - 0.5 / 4) * 24
    want = np.array([(0.5 / 6 - 0.5) * 36.0, (0.5 - 0.5 / 4) * 24.0, -50.0])
    np.testing.assert_allclose(dirs[0], want / np.linalg.norm(want), rtol=1e-12)
    ortho = Camera("/Cam", np.array([0.0, 0.0, 100.0]), np.eye(3), 50.0, 150.0, 150.0,
                   "orthographic")
    o_origins, o_dirs = ortho.rays(6, 4)
    assert o_origins.flags.writeable and len(np.unique(o_origins, axis=0)) == 24
    np.testing.assert_array_equal(o_dirs, np.broadcast_to([0.0, 0.0, -1.0], (24, 3)))


def test_an_orthographic_camera_sees_true_sizes_at_any_distance(tmp_path: Path) -> None:
    """A 40 mm square under a 150 mm wide orthographic view covers 40/150 of the frame
    each way, whatever the camera's height (USD's apertures in tenths of a unit)."""
    two = np.zeros((17 * 17, 2), np.float32)
    two[:, 0] = np.repeat(np.linspace(0, 1, 17), 17) < 0.5  # rows: y below the middle
    two[:, 1] = 1 - two[:, 0]
    asset = patch_asset(tmp_path / "asset", [deon_fit("low"), deon_fit("high")],
                        vertex_weights=two)
    options = RenderOptions(resolution=(96, 96), texture_size=128, light_samples=1,
                            aovs=("beauty", "region"), texture_outputs=("stretch", "region"))
    areas = []
    for height in (50.0, 400.0):
        images, _ = Renderer(open_stage_guarded(_ortho_scene(tmp_path, height, asset)),
                             options).render()
        areas.append(float(images["beauty"][..., 3].sum()))
        region = images["region"][..., 0]
        # the region AOV: -1 off the skin, region 0 in the lower half, 1 in the upper
        assert region[0, 0] == -1 and region[40, 48] == 1 and region[56, 48] == 0
    side = 96 * 40 / 150
    assert all(abs(a - side * side) <= 4 * side / 8 for a in areas)


def test_texture_space_outputs_hold_the_layout(tmp_path: Path) -> None:
    """<name>_uv.exr: stretch is the patch's mm per texel (40 mm over 128 texels), the
    region map is the vertex regions' argmax, coverage is the charts."""
    import OpenImageIO as oiio

    asset = patch_asset(tmp_path / "asset", [deon_fit()])
    scene = _ortho_scene(tmp_path, 100.0, asset)
    options = RenderOptions(resolution=(32, 32), texture_size=128, light_samples=1,
                            aovs=("beauty",),
                            texture_outputs=("irradiance", "radiosity", "stretch", "region"))
    doc = render_files(scene, tmp_path / "out", options)
    uv = tmp_path / "out" / "ortho_100_uv.exr"
    assert doc["frames"][0]["outputs"]["texture_space"] == [str(uv)]
    buf = oiio.ImageBuf(str(uv))
    names = list(buf.spec().channelnames)
    px = np.asarray(buf.get_pixels(oiio.FLOAT))
    assert {"radiosity.R", "irradiance.G", "stretch.u_mm", "region.id", "coverage.A"} <= \
        set(names)
    cov = px[..., names.index("coverage.A")] > 0
    assert cov.mean() > 0.95
    np.testing.assert_allclose(px[..., names.index("stretch.u_mm")][cov], 40 / 128, rtol=1e-3)
    np.testing.assert_allclose(px[..., names.index("stretch.v_mm")][cov], 40 / 128, rtol=1e-3)
    assert set(np.unique(px[..., names.index("region.id")][cov])) == {0.0}
    assert buf.spec().getattribute("oiio:ColorSpace") == "lin_ap1_scene"


def test_display_image_is_ocios_display_view_applied_at_once() -> None:
    """The PNG's display-referred pixels (applied in row bands on the cores) equal OCIO's
    own processor for the config's default display and view applied to the whole image
    at once, clipped to [0, 1]; NaN and +inf are made 0 and 1e4 first."""
    import PyOpenColorIO as OCIO

    from skinpipe.imageio import ocio_config
    from skinpipe.render.outputs import display_image

    rng = np.random.default_rng(1)
    beauty = np.concatenate([rng.random((37, 53, 3), np.float32) * 4,
                             np.ones((37, 53, 1), np.float32)], axis=2)
    beauty[0, 0, 0], beauty[1, 1, 1] = np.nan, np.inf
    pixels, info = display_image(beauty, "lin_ap1_scene", "ocio://default")
    config = ocio_config("ocio://default")
    proc = config.getProcessor(OCIO.DisplayViewTransform(
        src="lin_ap1_scene", display=info["display"], view=info["view"])).getDefaultCPUProcessor()
    whole = np.nan_to_num(beauty[..., :3], nan=0.0, posinf=1e4).astype(np.float32)
    proc.applyRGB(whole.reshape(-1, 3))
    np.testing.assert_array_equal(pixels, np.clip(whole, 0, 1))


def test_written_exr_and_png_read_back_as_ocios_display_of_the_beauty(tmp_path: Path
                                                                       ) -> None:
    """write_outputs writes the PNG on a thread beside the EXR: OpenImageIO reads the EXR
    back as the AOVs given, and the PNG (as stored: straight alpha) as OCIO's own display
    view of the EXR's premultiplied beauty divided by its alpha (background: 0), clipped
    and rounded to 8 bits, with the beauty's alpha; frames written at once into one
    folder keep their own pixels."""
    import OpenImageIO as oiio
    import PyOpenColorIO as OCIO

    from skinpipe.imageio import ocio_config
    from skinpipe.render.outputs import write_outputs

    rng = np.random.default_rng(4)
    frames = {f"f{i}": {"beauty": np.concatenate([rng.random((23, 31, 3), np.float32) * 3,
                                                  rng.random((23, 31, 1), np.float32)], 2),
                        "albedo": rng.random((23, 31, 3), np.float32)} for i in range(3)}
    for images in frames.values():
        images["beauty"][:4] = 0.0  # background rows: no coverage, no colour
    with ThreadPoolExecutor(3) as pool:
        infos = dict(zip(frames, pool.map(
            lambda kv: write_outputs(tmp_path, kv[0], kv[1], "lin_ap1_scene",
                                     "ocio://default"), frames.items()), strict=True))
    config = ocio_config("ocio://default")
    for name, images in frames.items():
        exr = oiio.ImageBuf(str(tmp_path / f"{name}.exr")).get_pixels(oiio.FLOAT)
        np.testing.assert_array_equal(exr[..., :4], images["beauty"])
        np.testing.assert_array_equal(exr[..., 4:], images["albedo"])
        info = infos[name]
        proc = config.getProcessor(OCIO.DisplayViewTransform(
            src="lin_ap1_scene", display=info["display"],
            view=info["view"])).getDefaultCPUProcessor()
        alpha = exr[..., 3:4]
        rgb = np.divide(exr[..., :3], alpha, out=np.zeros_like(exr[..., :3]),
                        where=alpha > 0)  # the colour, not times coverage
        proc.applyRGB(rgb.reshape(-1, 3))
        want = np.rint(np.clip(np.concatenate([rgb, alpha], 2).astype(np.float64), 0, 1)
                       * 255)
        straight = oiio.ImageSpec()  # as stored: PNG's alpha is not premultiplied
        straight.attribute("oiio:UnassociatedAlpha", 1)
        png = oiio.ImageBuf(str(tmp_path / f"{name}.png"), 0, 0, straight).get_pixels(
            oiio.UINT8)
        np.testing.assert_array_equal(png, want.astype(np.uint8))


def test_surface_flux_in_bands_is_the_whole_textures_sum() -> None:
    from skinpipe.render.shading import surface_flux

    pts, tris, uv = grid_patch(6, 30.0)
    maps = rasterize(pts, tris, uv * 0.8 + 0.1, tris, 50, 0.001)
    rgb = np.random.default_rng(3).random((50, 50, 3)).astype(np.float32)
    area = maps.mm_per_texel_u * maps.mm_per_texel_v * maps.coverage
    whole = float((area[..., None].astype(np.float64) * rgb).sum())
    for rows in (1, 7, 50, 256):  # bands that do and do not divide the rows
        assert surface_flux(rgb, maps, rows) == pytest.approx(whole, rel=1e-6)
        # with the stretch maps let go, the areas from the triangles': the same sum
        assert surface_flux(rgb, maps.without_surface(keep_stretch=False), rows) == \
            surface_flux(rgb, maps, rows)


def test_a_last_frame_writing_the_irradiance_texture_keeps_its_map(lit_patch: Path) -> None:
    from dataclasses import replace

    renderer = Renderer(open_stage_guarded(lit_patch),
                        replace(SMALL, texture_outputs=("irradiance",)))
    renderer.last_frame = True
    renderer.render()
    renderer.close()
    assert renderer.textures[0].irradiance_filled is not None
    assert renderer.textures[0].at_hits is None


@pytest.mark.parametrize("power", [0.5, 0.3, 0.0])
def test_albedo_weights_in_bands_are_the_whole_textures(power: float) -> None:
    from skinpipe.render.shading import times_albedo_power

    rng = np.random.default_rng(5)
    albedo = rng.random((37, 11, 3)).astype(np.float32)
    rgb = rng.random((37, 11, 3)).astype(np.float32)
    want = rgb * (np.sqrt(albedo) if power == 0.5 else np.power(albedo, power))
    got = rgb.copy()
    times_albedo_power(got, albedo, power, rows=5)
    np.testing.assert_array_equal(got, want)


def test_a_shared_view_names_its_display_colour_space() -> None:
    """OCIO 2.2+ configs share views across displays and answer ``<USE_DISPLAY_NAME>``
    for the colour space of such a view: the display's own colour space is meant."""
    from skinpipe.imageio import ocio_config
    from skinpipe.render.outputs import display_colorspace

    config = ocio_config("ocio://default")
    display = config.getDefaultDisplay()
    view = config.getDefaultView(display)
    assert config.getDisplayViewColorSpaceName(display, view) == "<USE_DISPLAY_NAME>"
    space = display_colorspace("ocio://default", display, view)
    assert space == display and config.getColorSpace(space) is not None
