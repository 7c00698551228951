"""Light arriving at an angle, through ``skinpipe render``, against the light tracer's lit
level of skin1 (tests/physics/light_tracer.py: the up-radiance under uniform light at
0-75 degrees), behind a smooth dielectric of index 1.4 and index-matched.

Behind index 1.4 the truth stays Lambertian within 5% up to 60 degrees and loses 11-16%
to Fresnel reflection at 75: the boundary's transmission relative to normal incidence
(skinpipe/render/light/boundary.py) must follow. Index-matched, skin1's single
scattering (a fifth to a half of its light) makes the truth 6-35% brighter at 75
degrees, less than the diffusion's depth factor alone gives (up to 17% too bright): the
angular law (skinpipe/render/light/reflection_law.py), with each region's medium
inverted from the profile's entry spike, must follow within 5% per channel. The profile
takes the user's road: the traced CSV through ``skinpipe fit`` at its defaults."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Gf, Sdf, UsdGeom, UsdLux

from skinpipe.cli import main
from skinpipe.profile.io import read_fit_json

from ..render_scenes import ortho_camera_down, patch_asset, render_diffuse, scene_over

PHYSICS = Path(__file__).parents[1] / "fixtures" / "physics"
ANGLES = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)


def _scene(tmp: Path, asset: Path, angle_deg: float, albedo: list[float]) -> Path:
    def build(stage) -> None:
        ortho_camera_down(stage, 20.0, 20.0)
        light = UsdLux.DistantLight.Define(stage, "/Sun")
        light.CreateIntensityAttr(1.0)
        light.CreateAngleAttr(0.0)
        # the light's -Z turned about Y: it arrives angle_deg from the normal
        UsdGeom.Xformable(light).AddRotateYOp().Set(angle_deg)
        shader = stage.OverridePrim("/Patch/Looks/SkinMaterial/PreviewSurface")
        shader.CreateAttribute("inputs:diffuseColor", Sdf.ValueTypeNames.Color3f).Set(
            Gf.Vec3f(*albedo))

    return scene_over(asset, tmp / f"scene_{angle_deg:g}.usda", build)


@pytest.mark.slow  # a fit and six renders: about 40 s a boundary
@pytest.mark.parametrize(("medium", "ior"), [("skin1_eta1.4", "1.4"), ("skin1", "1")])
def test_the_lit_level_follows_the_light_tracer_from_0_to_75_degrees(
        tmp_path: Path, medium: str, ior: str) -> None:
    truth = json.loads((PHYSICS / "totals.json").read_text())[medium]["channels"]
    lit = np.array([[c["lit_up_radiance"][str(a)] for c in truth] for a in ANGLES])
    albedo = (math.pi * lit[0]).tolist()  # the diffuse albedo at normal incidence
    fit = tmp_path / "fit.json"
    assert main(["fit", str(PHYSICS / f"{medium}.csv"), "-k", "6", "-o", str(fit)]) == 0
    asset = patch_asset(tmp_path / "asset", [read_fit_json(fit)], n=8, size_mm=40.0)
    got = []
    for angle in ANGLES:
        out = tmp_path / f"out_{angle:g}"
        scene = _scene(tmp_path, asset, angle, albedo)
        rgb = render_diffuse(scene, out, "--resolution", "16x16", "--texture-size", "256",
                             "--ior", ior, aovs="beauty,diffuse")
        got.append(rgb[6:10, 6:10].mean(axis=(0, 1)).astype(np.float64).tolist())
    got = np.asarray(got)
    cos = np.cos(np.radians(ANGLES))[:, None]
    # per unit irradiance normal to the light: the render's radiance against the tracer's
    # up-radiance per unit power times the surface's cos (and normal incidence's level)
    ratio = (got / got[0]) / (lit * cos / lit[0])
    assert np.all(np.abs(ratio - 1) < 0.05), np.round(ratio, 3).tolist()
    np.testing.assert_allclose(got[0], lit[0], rtol=0.01)  # the albedo as measured
