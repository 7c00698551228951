"""Regenerate tests/fixtures/usd: one clean skin asset and bad variants of it.

    python tools/make_usd_fixtures.py

Each bad asset is named after the one validation rule it must fail
(``bad/<Rule>[_<case>].usda``); tests check that it fails with that rule and no other.
The clean asset is a 3 x 2 quad patch with two regions, authored by skinpipe's own
author stage and flattened into one .usda file.
"""

from __future__ import annotations

import math
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
from pxr import Gf, Sdf, Usd, Vt

from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.profile.types import FitResult, MeasuredProfile
from skinpipe.usd.author import RegionAssignment, author_asset
from skinpipe.usd.mesh import MeshData

ROOT = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "usd"
PROFILE = "/Face/Looks/Profiles/forehead"
MESH = "/Face/Geom/Mesh"


def clean_stage() -> Usd.Stage:
    xs, ys = np.meshgrid(np.arange(4.0), np.arange(3.0))
    points = np.stack([xs.ravel() * 10, ys.ravel() * 10, np.zeros(12)], axis=1)
    quads = [[r * 4 + c, r * 4 + c + 1, (r + 1) * 4 + c + 1, (r + 1) * 4 + c]
             for r in range(2) for c in range(3)]
    mesh = MeshData(points, np.full(6, 4, np.int32), np.array(quads, np.int32).reshape(-1),
                    0.001)
    fits, measured = [], {}
    r = np.linspace(0.0, 2.0, 11)
    for name, scale in (("forehead", 1.0), ("cheek", 1.5)):
        v = DEON_2007_SKIN.variances_mm2 * scale
        fits.append(FitResult(name, v, DEON_2007_SKIN.weights, np.array([1e-3, 2e-3, 3e-3]),
                              0.4, "Solve_Succeeded", "ga+ipopt", 40, 1e-6, 6, "channels", 11,
                              (0.0, 2.0)))
        values = np.exp(-r[:, None] / np.array([0.9, 0.6, 0.4]) / scale)
        measured[name] = MeasuredProfile(r, values, 0.01 * values, name)
    face_region = np.array([0, 0, 0, 1, 1, 1], np.int32)
    weights = np.zeros((12, 2), np.float32)
    weights[:, 0] = np.where(points[:, 1] < 15, 1.0, 0.0)
    weights[:, 1] = 1.0 - weights[:, 0]
    regions = RegionAssignment(("forehead", "cheek"), face_region, weights)
    with tempfile.TemporaryDirectory() as tmp:
        paths = author_asset(fits, mesh, regions, tmp, measured=measured)
        flat = Usd.Stage.Open(str(paths.asset)).Flatten()
    return Usd.Stage.Open(flat)


def _attr(stage: Usd.Stage, path: str) -> Usd.Attribute:
    prim_path, _, name = path.rpartition(".")
    return stage.GetPrimAtPath(prim_path).GetAttribute(name)


def _retype(stage: Usd.Stage, path: str, type_name: Sdf.ValueTypeName) -> None:
    prim_path, _, name = path.rpartition(".")
    prim = stage.GetPrimAtPath(prim_path)
    value = prim.GetAttribute(name).Get()
    prim.RemoveProperty(name)
    prim.CreateAttribute(name, type_name).Set(value)


BREAKS: dict[str, Callable[[Usd.Stage], None]] = {
    # a float3 where OpenPBR's base_color is color3 (MaterialX's node definition)
    "MaterialXNetworkValid": lambda s: _retype(
        s, "/Face/Looks/SkinMaterial/OpenPBR.inputs:base_color", Sdf.ValueTypeNames.Float3),
    "ColorSpaceNamed": lambda s: s.GetPrimAtPath("/Face").RemoveAPI(Usd.ColorSpaceAPI),
    "ProfileRegionNamed": lambda s: _attr(s, f"{PROFILE}.region").Set(""),
    "ProfileArrayLengths": lambda s: _attr(s, f"{PROFILE}.weights").Set(
        Vt.Vec3fArray([Gf.Vec3f(0.5, 0.5, 0.5)] * 2 + [Gf.Vec3f(0, 0, 0)] * 5)),
    "ProfileArrayLengths_measured": lambda s: _attr(s, f"{PROFILE}.measured:stddev").Set(
        Vt.Vec3fArray([Gf.Vec3f(0.01, 0.01, 0.01)] * 3)),
    "ProfileVariancesValid": lambda s: _attr(s, f"{PROFILE}.variances").Set(
        Vt.FloatArray([-0.0064, 0.0484, 0.187, 0.567, 1.99, 7.41])),
    "ProfileVariancesValid_unsorted": lambda s: _attr(s, f"{PROFILE}.variances").Set(
        Vt.FloatArray([0.0484, 0.0064, 0.187, 0.567, 1.99, 7.41])),
    # the seed paper's printed forehead table: its G row sums to 1.0926
    "ProfileWeightsNormalized": lambda s: _attr(s, f"{PROFILE}.weights").Set(Vt.Vec3fArray(
        [Gf.Vec3f(0.2717, 0.1017, 0.6749), Gf.Vec3f(0.1025, 0.4005, 0.2810),
         Gf.Vec3f(0.1001, 0.3784, 0.0), Gf.Vec3f(0.1256, 0.2019, 0.0441),
         Gf.Vec3f(0.3300, 0.0101, 0.0), Gf.Vec3f(0.0701, 0.0, 0.0)])),
    "ProfileWeightsNormalized_negative": lambda s: _attr(s, f"{PROFILE}.weights").Set(
        Vt.Vec3fArray([Gf.Vec3f(1.1, 1, 1), Gf.Vec3f(-0.1, 0, 0)] + [Gf.Vec3f(0, 0, 0)] * 4)),
    "ProfileFitErrorValid": lambda s: _attr(s, f"{PROFILE}.fit:error").Set(
        Gf.Vec3f(math.nan, 0.001, 0.001)),
    "MeasuredSamplesFinite": lambda s: _attr(s, f"{PROFILE}.measured:values").Set(
        Vt.Vec3fArray([Gf.Vec3f(math.nan, 1, 1)] + [Gf.Vec3f(1, 1, 1)] * 10)),
    "RegionsApiOnMesh": lambda s: s.GetPrimAtPath("/Face/Geom").ApplyAPI(
        "SkinProfileRegionsAPI"),
    "RegionProfilesTargetsValid": lambda s: s.GetPrimAtPath(MESH).GetRelationship(
        "skin:profiles").SetTargets([Sdf.Path(PROFILE), Sdf.Path("/Face/Looks/Profiles/gone")]),
    "RegionIndexValid": lambda s: _attr(s, f"{MESH}.primvars:skin:regionIndex").Set(
        Vt.IntArray([0, 0, 0, 1, 1, 2])),
    "RegionIndexValid_count": lambda s: _attr(s, f"{MESH}.primvars:skin:regionIndex").Set(
        Vt.IntArray([0, 0, 0, 1, 1])),
    "RegionWeightsValid": lambda s: _attr(s, f"{MESH}.primvars:skin:regionWeights").Set(
        Vt.FloatArray([0.7, 0.7] + [1.0, 0.0] * 11)),
    # both subsets valid as a partition, but swapped against the region index
    "RegionSubsetsPartition": lambda s: (
        _attr(s, f"{MESH}/forehead.indices").Set(Vt.IntArray([3, 4, 5])),
        _attr(s, f"{MESH}/cheek.indices").Set(Vt.IntArray([0, 1, 2]))),
}


def main() -> None:
    shutil.rmtree(ROOT, ignore_errors=True)
    (ROOT / "clean").mkdir(parents=True)
    (ROOT / "bad").mkdir(parents=True)
    clean_stage().GetRootLayer().Export(str(ROOT / "clean" / "two_regions.usda"))
    for name, brk in BREAKS.items():
        stage = clean_stage()
        brk(stage)
        stage.GetRootLayer().Export(str(ROOT / "bad" / f"{name}.usda"))
    nested = "#usda 1.0\n\ndef \"Deep\" {\n    custom int[] a = " + "[" * 60000 + \
        "]" * 60000 + "\n}\n"
    (ROOT / "unreadable_nested.usda").write_text(nested)
    print(f"wrote {ROOT}: 1 clean, {len(BREAKS)} bad, 1 unreadable")


if __name__ == "__main__":
    main()
