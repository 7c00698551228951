"""A shot layer for an asset: camera and lights, kept out of the asset itself.

``OUT/scene.usda`` has one default prim, ``/Shot``, holding the asset by reference
(``/Shot/<asset>``: referencing the shot brings the face, the camera and the lights, and
one asset can be placed twice), ``/Shot/Camera`` framing the asset's bounds from the
front, a key SphereLight (soft shadows) and a dim DomeLight fill. With
``turntable_frames`` the camera orbits the asset once over frames 1..N.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLux

from ..errors import InputError
from .io import export_layer_atomic, open_stage_guarded
from .schema import WORKING_COLORSPACE


@dataclass(frozen=True)
class ShotOptions:
    key_intensity: float = 3.0
    key_radius_fraction: float = 0.08
    """Key light radius as a fraction of the asset's bounding diagonal (soft shadows)."""
    fill_intensity: float = 0.15
    focal_length: float = 50.0
    """Lens focal length, mm (written in USD's tenths of a scene unit)."""
    horizontal_aperture: float = 24.0
    """Film back width (and height), mm."""
    turntable_frames: int = 0
    margin: float = 1.15

    def __post_init__(self) -> None:
        for name in ("key_intensity", "fill_intensity"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v <= 1e6):
                raise InputError(f"{name.replace('_', '-')} must be a finite number in "
                                 f"0-1e6, got {v}")
        for name in ("key_radius_fraction", "focal_length", "horizontal_aperture", "margin"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 < v <= 1e4):
                raise InputError(f"{name.replace('_', '-')} must be a finite number > 0, "
                                 f"got {v}")
        if not 0 <= self.turntable_frames <= 100_000:
            raise InputError("turntable must be 0 (a still) or a number of frames up to "
                             f"100000, got {self.turntable_frames}")


def camera_tenths_per_mm(meters_per_unit: float) -> float:
    """USD camera lengths (focalLength, apertures) are in tenths of a scene unit: the
    value for one millimetre on a stage of ``meters_per_unit`` (10 on a millimetre stage,
    so a 50 mm lens is focalLength 500)."""
    return 10.0 * 0.001 / meters_per_unit


def author_shot(asset: Path, out: Path, options: ShotOptions = ShotOptions()) -> Path:
    """Write ``out`` (a .usda shot layer over ``asset``); the asset is only read."""
    asset = Path(asset)
    out = Path(out)
    if out.suffix.lower() not in (".usda", ".usd", ".usdc"):
        raise InputError(f"a shot layer is written as USD: the output must end in .usda, "
                         f".usd or .usdc, not {out.suffix or 'no suffix'!r}", out)
    if out.resolve() == asset.resolve():
        raise InputError("the shot layer would overwrite the asset", out)
    src = open_stage_guarded(asset)
    cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    box = cache.ComputeWorldBound(src.GetPseudoRoot()).ComputeAlignedRange()
    if box.IsEmpty():
        raise InputError("the asset has no geometry with extent to frame", asset)
    lo, hi = np.array(box.GetMin()), np.array(box.GetMax())
    centre, size = (lo + hi) / 2, hi - lo
    diag = float(np.linalg.norm(size))
    up_axis = UsdGeom.GetStageUpAxis(src)
    if up_axis != UsdGeom.Tokens.y:
        raise InputError(f"shot framing supports Y-up assets, this one is {up_axis}-up", asset)
    # distance at which the larger of width/height fills the frame (with a margin)
    fov = 2 * math.atan(0.5 * options.horizontal_aperture / options.focal_length)
    dist = options.margin * 0.5 * max(size[0], size[1]) / math.tan(fov / 2) + size[2] / 2

    layer = Sdf.Layer.CreateAnonymous("scene.usda")
    # the prims are authored through a stage that is gone before the asset is referenced
    # (a stage on the anonymous layer would try to compose the relative reference)
    _author_shot_prims(layer, src, options, centre, dist, diag, up_axis)
    root = src.GetDefaultPrim()
    if not root:
        raise InputError("the asset has no defaultPrim to reference", asset)
    # the reference is added to the bare layer: no stage composes the asset from here
    spec = Sdf.CreatePrimInLayer(layer, f"/Shot/{root.GetName()}")
    spec.specifier = Sdf.SpecifierDef
    spec.referenceList.Prepend(Sdf.Reference(os.path.relpath(asset.resolve(),
                                                             out.resolve().parent)))
    export_layer_atomic(layer, out)
    return out


def _author_shot_prims(layer: Any, src: Any, options: ShotOptions, centre: Any, dist: float,
                       diag: float, up_axis: str) -> None:
    """Camera, lights and the shot's metadata on ``layer``."""
    stage = Usd.Stage.Open(layer)
    UsdGeom.SetStageMetersPerUnit(stage, UsdGeom.GetStageMetersPerUnit(src))
    UsdGeom.SetStageUpAxis(stage, up_axis)
    shot = UsdGeom.Xform.Define(stage, "/Shot").GetPrim()
    Usd.ColorSpaceAPI.Apply(shot).CreateColorSpaceNameAttr(WORKING_COLORSPACE)
    cam = UsdGeom.Camera.Define(stage, "/Shot/Camera")
    tenths = camera_tenths_per_mm(UsdGeom.GetStageMetersPerUnit(src))
    cam.CreateFocalLengthAttr(options.focal_length * tenths)
    cam.CreateHorizontalApertureAttr(options.horizontal_aperture * tenths)
    cam.CreateVerticalApertureAttr(options.horizontal_aperture * tenths)
    cam.CreateClippingRangeAttr(Gf.Vec2f(float(dist * 0.05), float(dist * 10)))
    orbit = cam.AddRotateYOp(opSuffix="orbit")
    move = cam.AddTranslateOp(opSuffix="dolly")
    # ops apply right to left on points: dolly back along +Z, then orbit about the centre
    pivot = UsdGeom.Xformable(cam).AddTranslateOp(opSuffix="pivot")
    UsdGeom.Xformable(cam).SetXformOpOrder([pivot, orbit, move])
    pivot.Set(Gf.Vec3d(*centre))
    move.Set(Gf.Vec3d(0.0, 0.0, float(dist)))
    if options.turntable_frames > 0:
        n = options.turntable_frames
        for f in range(1, n + 1):
            orbit.Set(360.0 * (f - 1) / n, Usd.TimeCode(f))
        stage.SetStartTimeCode(1)
        stage.SetEndTimeCode(n)
    else:
        orbit.Set(0.0)
    UsdGeom.Scope.Define(stage, "/Shot/Lights")
    key = UsdLux.SphereLight.Define(stage, "/Shot/Lights/Key")
    key.CreateIntensityAttr(options.key_intensity)
    key.CreateRadiusAttr(options.key_radius_fraction * diag)
    key.CreateColorAttr(Gf.Vec3f(1.0, 0.97, 0.92))
    key_pos = centre + np.array([-0.8, 0.6, 1.2]) * dist
    UsdGeom.Xformable(key).AddTranslateOp().Set(Gf.Vec3d(*key_pos))
    # the sphere's radiance is intensity: scale it so irradiance at the face is ~ intensity
    solid = 2 * math.pi * (1 - math.sqrt(max(0.0, 1 - (options.key_radius_fraction * diag /
                                                       np.linalg.norm(key_pos - centre)) ** 2)))
    key.GetIntensityAttr().Set(float(options.key_intensity / max(solid, 1e-9)))
    fill = UsdLux.DomeLight.Define(stage, "/Shot/Lights/Fill")
    fill.CreateIntensityAttr(options.fill_intensity)
    fill.CreateColorAttr(Gf.Vec3f(0.85, 0.9, 1.0))
    stage.SetDefaultPrim(stage.GetPrimAtPath("/Shot"))
    layer.customLayerData = {"skinpipe:colorSpace": WORKING_COLORSPACE,
                             "skinpipe:generator": "skinpipe shot"}
