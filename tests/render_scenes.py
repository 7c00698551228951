"""Small USD scenes for render tests: flat patches and spheres with exact profiles."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.profile.types import FitResult
from skinpipe.usd.author import RegionAssignment, author_asset
from skinpipe.usd.mesh import MeshData


def exact_fit(name: str, variances_mm2: Any, weights: Any) -> FitResult:
    """A FitResult holding given terms (weights normalised per channel)."""
    v = np.asarray(variances_mm2, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum(axis=0, keepdims=True)
    return FitResult(name=name, variances_mm2=v, weights=w, error=np.zeros(3), seconds=0.0,
                     status="exact", solver="none", iterations=0, objective=0.0,
                     k_requested=v.size, share="none", n_samples=0, radius_range_mm=(0.0, 8.0))


def deon_fit(name: str = "skin", scale: float = 1.0) -> FitResult:
    return exact_fit(name, DEON_2007_SKIN.variances_mm2 * scale, DEON_2007_SKIN.weights)


PHYSICS = Path(__file__).parent / "fixtures" / "physics"


def skin1_asset(tmp: Path, mesh_obj: Path, landmark_mm: list[float], asset: Path) -> Path:
    """skin1's profile CSV through ``fit`` (into ``tmp``/fits, once) and ``mesh_obj``
    through ``author`` into ``asset`` (once), its one region skin1 at ``landmark_mm``:
    the user's road to a skin1 asset. Returns the asset's folder."""
    from skinpipe.cli import main

    fits = tmp / "fits"
    if not fits.exists():
        fits.mkdir()
        assert main(["fit", str(PHYSICS / "skin1.csv"), "-k", "6",
                     "-o", str(fits / "skin1.json")]) == 0
    if not asset.exists():
        landmarks = tmp / "landmarks.json"
        landmarks.write_text(json.dumps({"regions": {"skin1": [list(landmark_mm)]}}))
        assert main(["author", "--fits", str(fits), "--mesh", str(mesh_obj), "--landmarks",
                     str(landmarks), "-o", str(asset)]) == 0
    return asset


def paint_skin1_albedo(stage: Any) -> None:
    """The skin's diffuse colour over ``stage``: skin1's measured albedo (pi x the traced
    radiance lit from above, fixtures/physics/totals.json)."""
    from pxr import Gf, Sdf

    totals = json.loads((PHYSICS / "totals.json").read_text())["skin1"]["channels"]
    albedo = [math.pi * c["lit_up_radiance"]["0.0"] for c in totals]
    for shader in ("/Face/Looks/SkinMaterial/PreviewSurface",
                   "/Face/Looks/Regions/skin1/PreviewSurface"):
        stage.OverridePrim(shader).CreateAttribute(
            "inputs:diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*albedo))


def grid_patch(n: int, size_mm: float, z: float = 0.0
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """An n x n quad grid split into triangles on z = const, centred at the origin, in mm;
    returns points, triangles and per-vertex uv in [0, 1]."""
    xs, ys = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1))
    uv = np.stack([xs.ravel(), ys.ravel()], axis=1)
    pts = np.stack([(uv[:, 0] - 0.5) * size_mm, (uv[:, 1] - 0.5) * size_mm,
                    np.full(uv.shape[0], z)], axis=1)
    tris = []
    for r in range(n):
        for c in range(n):
            a = r * (n + 1) + c
            tris += [[a, a + 1, a + n + 2], [a, a + n + 2, a + n + 1]]
    return pts, np.array(tris, np.int32), uv


def patch_asset(out: Path, fits: list[FitResult], n: int = 16, size_mm: float = 40.0,
                vertex_weights: np.ndarray | None = None, with_uv: bool = True) -> Path:
    pts, tris, uv = grid_patch(n, size_mm)
    mesh = MeshData(pts, np.full(tris.shape[0], 3, np.int32), tris.reshape(-1), 0.001,
                    uv if with_uv else None)
    if vertex_weights is None:
        vertex_weights = np.zeros((pts.shape[0], len(fits)), np.float32)
        vertex_weights[:, 0] = 1
    face_region = np.argmax(vertex_weights[tris].mean(axis=1), axis=1).astype(np.int32)
    regions = RegionAssignment(tuple(f.name for f in fits), face_region,
                               vertex_weights.astype(np.float32))
    return author_asset(fits, mesh, regions, out, name="Patch", up_axis="Z").asset


def render_diffuse(scene: Path, out: Path, *options: str, aovs: str = "diffuse"
                   ) -> NDArray[np.float32]:
    """``skinpipe render`` of ``scene`` into ``out`` with ``options`` (and ``--aovs
    aovs``), its diffuse AOV read back with OpenImageIO: (H, W, 3)."""
    import OpenImageIO as oiio

    from skinpipe.cli import main

    assert main(["render", str(scene), "-o", str(out), "--aovs", aovs, *options]) == 0
    buf = oiio.ImageBuf(str(out / f"{scene.stem}.exr"))
    names = list(buf.spec().channelnames)
    px = np.asarray(buf.get_pixels(oiio.FLOAT))
    return np.stack([px[..., names.index(f"diffuse.{c}")] for c in "RGB"], axis=-1)


def scene_over(asset: Path, out: Path, build: Callable[[Any], None]) -> Path:
    """A scene.usda sublayering ``asset`` with whatever ``build(stage)`` adds."""
    from pxr import Sdf, Usd, UsdGeom

    layer = Sdf.Layer.CreateNew(str(out))
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, "Z")
    build(stage)
    del stage
    layer.subLayerPaths = [str(asset)]
    layer.Save()
    return out


def top_camera(stage: Any, height: float = 100.0, aperture: float = 45.0) -> None:
    """A camera above the patch looking down -Z."""
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateFocalLengthAttr(50.0)
    cam.CreateHorizontalApertureAttr(aperture)
    cam.CreateVerticalApertureAttr(aperture)
    UsdGeom.Xformable(cam).AddTranslateOp().Set(Gf.Vec3d(0, 0, height))


def ortho_camera_down(stage: Any, width_mm: float, height_mm: float,
                      z: float = 100.0) -> Any:
    """An orthographic camera at height ``z`` looking down -Z over ``width_mm`` x
    ``height_mm`` (apertures in USD's tenths of a scene unit)."""
    from pxr import Gf, UsdGeom

    cam = UsdGeom.Camera.Define(stage, "/Cam")
    cam.CreateProjectionAttr(UsdGeom.Tokens.orthographic)
    cam.CreateHorizontalApertureAttr(10.0 * width_mm)
    cam.CreateVerticalApertureAttr(10.0 * height_mm)
    UsdGeom.Xformable(cam).AddTranslateOp().Set(Gf.Vec3d(0, 0, z))
    return cam


def hidden_blocker(stage: Any, corners: list[tuple[float, float]], z: float = 10.0) -> Any:
    """A quad over ``corners`` (x, y) at height ``z`` that casts shadows and that the
    camera does not see."""
    from pxr import Gf, Sdf, UsdGeom

    from skinpipe.usd.schema import CAMERA_VISIBILITY_PRIMVAR

    blocker = UsdGeom.Mesh.Define(stage, "/Blocker")
    blocker.CreatePointsAttr([Gf.Vec3f(float(x), float(y), z) for x, y in corners])
    blocker.CreateFaceVertexCountsAttr([4])
    blocker.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
    UsdGeom.PrimvarsAPI(blocker).CreatePrimvar(
        CAMERA_VISIBILITY_PRIMVAR, Sdf.ValueTypeNames.Bool, UsdGeom.Tokens.constant).Set(False)
    return blocker


def distant_down(stage: Any, path: str = "/Sun", intensity: float = 1.0,
                 angle: float = 0.0) -> Any:
    from pxr import UsdLux

    light = UsdLux.DistantLight.Define(stage, path)
    light.CreateIntensityAttr(intensity)
    light.CreateAngleAttr(angle)
    return light
