"""The demo's painted albedo as OpenImageIO reads it back: a tiled, MIP-mapped half-float
OpenEXR with ACEScg chromaticities, freckles on it, and one colour per surface point, so
that a texel on either side of a UV seam has the same albedo."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest
from scipy.spatial import cKDTree

from skinpipe.imageio import ACESCG, CHROMATICITIES
from skinpipe.render.surface.texture_maps import rasterize
from skinpipe.render.surface.unwrap import triangulate
from skinpipe.render.surface.uvs import ensure_skin_uvs
from skinpipe.workflow.albedo import ALBEDO_NAME, REGION_TONES


def test_demo_albedo_reads_back_as_a_texture(demo_run: tuple[Path, str, str]) -> None:
    path = demo_run[0] / "asset" / ALBEDO_NAME
    image = oiio.ImageInput.open(str(path))
    assert image is not None, oiio.geterror()
    try:
        spec = image.spec()
        assert spec.tile_width > 0 and spec.format == oiio.TypeDesc("half")
        assert spec.getattribute("oiio:ColorSpace") == ACESCG
        np.testing.assert_allclose(spec.getattribute("chromaticities"),
                                   CHROMATICITIES[ACESCG], atol=1e-6)
        levels = 0
        while image.seek_subimage(0, levels):
            levels += 1
        assert levels == int(np.log2(spec.width)) + 1
    finally:
        image.close()


def test_demo_albedo_is_bound_as_linear_data(demo_run: tuple[Path, str, str]) -> None:
    """The UsdUVTexture says "raw" (no transfer function: an importer that reads "auto"
    as sRGB, as Blender 5.0 does, would darken it), and its file names ACEScg."""
    from pxr import Usd, UsdShade

    stage = Usd.Stage.Open(str(demo_run[0] / "asset" / "asset.usda"))
    textures = [UsdShade.Shader(p) for p in stage.Traverse()
                if UsdShade.Shader(p) and UsdShade.Shader(p).GetShaderId() == "UsdUVTexture"]
    assert len(textures) == 7  # the mesh's material and each region's
    for texture in textures:
        assert texture.GetInput("sourceColorSpace").Get() == "raw"
        assert texture.GetInput("file").GetAttr().GetColorSpace() == "lin_ap1_scene"


def _landmark_faces(mesh: object) -> dict[str, tuple[int, np.ndarray]]:
    """Per region of the sample landmarks: the face of ``mesh`` (a UsdGeom.Mesh) whose
    centre is nearest the region's first landmark, and that face's corners (indices into
    its face-vertex list)."""
    from pxr import UsdGeom

    from skinpipe.package_data import package_folder
    from skinpipe.usd.author import read_landmarks

    points = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get())
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    centres = np.array([points[indices[a:a + n]].mean(axis=0)
                        for a, n in zip(starts, counts, strict=True)])
    to_local = np.asarray(UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(0)
                          .GetInverse())
    out = {}
    landmarks = read_landmarks(package_folder("samples", "face") / "landmarks.json")
    for region, where in landmarks.items():
        first = np.asarray(where, np.float64).reshape(-1, 3)[0]
        local = (np.append(first, 1.0) @ to_local)[:3]
        face = int(np.argmin(np.linalg.norm(centres - local, axis=1)))
        out[region] = (face, np.arange(starts[face], starts[face] + counts[face]))
    return out


def test_demo_openpbr_differs_by_region_at_each_landmark(
        demo_run: tuple[Path, str, str]) -> None:
    """At each region's landmark, the face nearest it is bound (through its materialBind
    GeomSubset) to an OpenPBR network whose subsurface is that region's medium, textured
    by the albedo, and no two regions share a mean free path."""
    from pxr import Usd, UsdGeom, UsdShade

    stage = Usd.Stage.Open(str(demo_run[0] / "asset" / "asset.usda"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Geom/Mesh"))
    subsets = UsdShade.MaterialBindingAPI(mesh.GetPrim()).GetMaterialBindSubsets()
    radii = {}
    for region, (face, _) in _landmark_faces(mesh).items():
        (subset,) = [s for s in subsets if face in set(s.GetIndicesAttr().Get())]
        material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        openpbr = UsdShade.Shader(stage.GetPrimAtPath(f"{material.GetPath()}/OpenPBR"))
        mfp = np.array(stage.GetPrimAtPath(f"/Face/Looks/Profiles/{region}")
                       .GetAttribute("medium:meanFreePathMm").Get())
        radius = openpbr.GetInput("subsurface_radius").Get()
        scale = np.array(openpbr.GetInput("subsurface_radius_scale").Get())
        np.testing.assert_allclose(radius * scale * 1000 * UsdGeom.GetStageMetersPerUnit(
            stage), mfp, rtol=1e-5)
        assert openpbr.GetInput("subsurface_color").HasConnectedSource()
        radii[region] = round(radius, 4)
    assert len(radii) == 6 and len(set(radii.values())) == 6, radii


def test_demo_albedo_agrees_across_seams_and_has_freckles(
        demo_run: tuple[Path, str, str]) -> None:
    """Texel pairs far apart in UV (other charts) but within 0.3 texel on the surface read
    the same albedo from the file: spots and tone are painted on the surface. (Measured:
    95th percentile 0.0005, worst 0.015 over 449 pairs; the same texels against their
    neighbour three texels over differ by 0.024 at the 95th percentile.)"""
    asset = demo_run[0] / "asset" / "asset.usda"
    albedo = oiio.ImageBuf(str(asset.parent / ALBEDO_NAME)).get_pixels(oiio.FLOAT)[::-1]
    _, scene, mesh, uv, uv_tris, _ = ensure_skin_uvs(asset)
    maps = rasterize(mesh.mesh.points, triangulate(mesh.mesh), uv, uv_tris, albedo.shape[0],
                     scene.meters_per_unit, mesh.region_weights)
    covered = np.argwhere(maps.triangle >= 0)
    pos = maps.position[maps.triangle >= 0].astype(np.float64)
    texel_mm = float(np.median(maps.mm_per_texel_u[maps.triangle >= 0]))
    pairs = cKDTree(pos).query_pairs(0.3 * texel_mm / (scene.meters_per_unit * 1000.0),
                                     output_type="ndarray")
    far_in_uv = np.abs(covered[pairs[:, 0]] - covered[pairs[:, 1]]).max(1) > 8
    pairs = pairs[far_in_uv]
    assert len(pairs) > 100  # the demo's unwrap has seams
    a, b = (albedo[tuple(covered[pairs[:, k]].T)] for k in (0, 1))
    difference = np.abs(a - b).max(1)
    assert np.percentile(difference, 95) < 0.004 and difference.max() < 0.03
    # the tone (a blend of the regions') scales R, G and B alike; freckles (tint
    # 0.74/0.62) and moles redden R/G on 0.1-10% of the skin
    covered_mask = maps.triangle >= 0
    tones = np.array([REGION_TONES[n] for n in mesh.region_names])
    tone = maps.region_weights[covered_mask] @ tones
    values = albedo[covered_mask]
    redder = (values[:, 0] / np.maximum(values[:, 1], 1e-6)) / (tone[:, 0] / tone[:, 1])
    assert np.median(redder) == pytest.approx(1.0, abs=0.01)
    freckled = (redder > 1.08).mean()
    assert 0.001 < freckled < 0.1, freckled


def test_demo_blended_look_paints_each_region_medium_at_its_landmark(
        demo_run: tuple[Path, str, str]) -> None:
    """In the skinLook variant ``blended`` every subset falls back to the mesh's
    SkinMaterial, whose subsurface reads the painted maps: read back at each region's
    landmark (its face's UV), radius x scale is the regions' mean free paths blended by
    the mesh's region weights there (within 2%), and the six differ."""
    from pxr import Usd, UsdGeom, UsdShade

    from skinpipe.workflow.albedo import SUBSURFACE_SCALE_NAME

    folder = demo_run[0] / "asset"
    stage = Usd.Stage.Open(str(folder / "asset.usda"))
    stage.GetPrimAtPath("/Face").GetVariantSet("skinLook").SetVariantSelection("blended")
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Face/Geom/Mesh"))
    for subset in UsdShade.MaterialBindingAPI(mesh.GetPrim()).GetMaterialBindSubsets():
        material, _ = UsdShade.MaterialBindingAPI(subset.GetPrim()).ComputeBoundMaterial()
        assert material.GetPath() == "/Face/Looks/SkinMaterial"
    openpbr = UsdShade.Shader(stage.GetPrimAtPath("/Face/Looks/SkinMaterial/OpenPBR"))
    assert openpbr.GetInput("subsurface_radius_scale").HasConnectedSource()
    assert openpbr.GetInput("subsurface_color").HasConnectedSource()
    radius = openpbr.GetInput("subsurface_radius").Get()
    points = np.asarray(mesh.GetPointsAttr().Get(), np.float64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get())
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    uv = np.asarray(st.ComputeFlattened(), np.float64)
    per_corner = st.GetInterpolation() == UsdGeom.Tokens.faceVarying
    scale_map = oiio.ImageBuf(str(folder / SUBSURFACE_SCALE_NAME)).get_pixels(oiio.FLOAT)
    size = scale_map.shape[0]
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    targets = mesh.GetPrim().GetRelationship("skin:profiles").GetTargets()
    media = np.array([stage.GetPrimAtPath(t).GetAttribute("medium:meanFreePathMm").Get()
                      for t in targets], np.float64)
    weights = np.asarray(UsdGeom.PrimvarsAPI(mesh).GetPrimvar("skin:regionWeights")
                         .ComputeFlattened(), np.float64).reshape(points.shape[0], -1)
    seen = {}
    for region, (_, corners) in _landmark_faces(mesh).items():
        u, v = uv[corners if per_corner else indices[corners]].mean(axis=0)
        texel = scale_map[int((1 - v) * size), int(u * size)]
        blend = weights[indices[corners]].mean(axis=0)
        np.testing.assert_allclose(radius * texel * mpu * 1000, blend @ media, rtol=0.02)
        seen[region] = round(float(texel[0]), 3)
    assert len(set(seen.values())) == 6, seen
