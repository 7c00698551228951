"""Shot layers: they pass skinpipe validate (the colour space named on /Shot) and write
camera lengths in USD's convention (tenths of a scene unit)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdGeom

from skinpipe.profile.io import read_fit_json
from skinpipe.usd.author import RegionAssignment, author_asset
from skinpipe.usd.shot import ShotOptions, author_shot, camera_tenths_per_mm
from skinpipe.usd.validate import validate_file

from .test_author import _patch, fit_files  # noqa: F401  (fixture)


@pytest.fixture
def shot(fit_files: Path, tmp_path: Path) -> Path:  # noqa: F811
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("forehead", "cheek"), np.array([0] * 6 + [1] * 6, np.int32))
    asset = author_asset(fits, _patch(), regions, tmp_path / "a").asset
    return author_shot(asset, tmp_path / "scene.usda")


def test_shot_layer_validates(shot: Path) -> None:
    report = validate_file(shot)
    assert not report.failed(strict=False), report.problems
    assert not [p for p in report.problems if p.rule == "skinpipe:ColorSpaceNamed"]


def test_camera_lengths_in_tenths_of_a_scene_unit(shot: Path) -> None:
    stage = Usd.Stage.Open(str(shot))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.001
    cam = UsdGeom.Camera(stage.GetPrimAtPath("/Shot/Camera"))
    # a 50 mm lens on a 24 mm film back, on a millimetre stage: 500 and 240
    assert cam.GetFocalLengthAttr().Get() == pytest.approx(500.0)
    assert cam.GetHorizontalApertureAttr().Get() == pytest.approx(240.0)
    # USD's own camera math reads the same field of view as 50 mm over 24 mm
    fov = cam.GetCamera().GetFieldOfView(cam.GetCamera().FOVHorizontal)
    assert fov == pytest.approx(math.degrees(2 * math.atan(12 / 50)), rel=1e-6)
    assert ShotOptions().focal_length == 50.0


def test_tenths_per_mm() -> None:
    assert camera_tenths_per_mm(0.001) == pytest.approx(10.0)
    assert camera_tenths_per_mm(0.01) == pytest.approx(1.0)
    assert camera_tenths_per_mm(1.0) == pytest.approx(0.01)


def test_referencing_the_shot_brings_face_camera_and_lights(shot: Path) -> None:
    stage = Usd.Stage.CreateInMemory()
    for take in ("Take1", "Take2"):  # one asset placed twice
        stage.DefinePrim(f"/World/{take}").GetReferences().AddReference(str(shot))
    kinds = {(p.GetPath().pathElementCount > 1 and str(p.GetPath()).split("/")[2],
              p.GetTypeName()) for p in stage.Traverse()}
    for take in ("Take1", "Take2"):
        assert {(take, "Mesh"), (take, "Camera"), (take, "SphereLight"),
                (take, "DomeLight")} <= kinds
