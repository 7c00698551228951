"""Authoring: FIT.json -> USD -> read back is an identity; structure and safety."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from pxr import Gf, Kind, Sdf, Usd, UsdGeom

from skinpipe.cli import main
from skinpipe.errors import InputError
from skinpipe.profile.fit import fit_sum_of_gaussians
from skinpipe.profile.io import read_fit_json, write_fit_json
from skinpipe.usd.author import (
    RegionAssignment,
    assign_regions_from_landmarks,
    author_asset,
    read_landmarks,
    read_profiles,
)
from skinpipe.usd.mesh import MeshData, load_mesh, pymeshlab_face_scan
from skinpipe.usd.schema import schema_is_registered
from skinpipe.usd.validate import NOT_APPLICABLE, validate_file

from ..reference_profiles import deon_profile, dipole_normalised

SAMPLE_LANDMARKS = Path(__file__).parents[2] / "skinpipe" / "samples" / "face" / "landmarks.json"


def _patch() -> MeshData:
    xs, ys = np.meshgrid(np.arange(5.0), np.arange(4.0))
    pts = np.stack([xs.ravel(), ys.ravel(), np.zeros(20)], axis=1) * 10.0
    quads = [[r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c + 1, (r + 1) * 5 + c]
             for r in range(3) for c in range(4)]
    return MeshData(pts, np.full(12, 4, np.int32), np.array(quads, np.int32).reshape(-1), 0.001)


@pytest.fixture(scope="module")
def fit_files(tmp_path_factory: pytest.TempPathFactory) -> Path:
    d = tmp_path_factory.mktemp("fits")
    for name, prof in (("forehead", deon_profile()), ("cheek", dipole_normalised("skin1"))):
        fit = fit_sum_of_gaussians(prof, k=4, seed=1)
        fit.name = name
        write_fit_json(d / f"{name}.json", fit)
    return d


def test_schema_is_registered_on_import() -> None:
    assert schema_is_registered()


def test_round_trip_identical_numbers(fit_files: Path, tmp_path: Path) -> None:
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("cheek", "forehead"),
                               np.array([0] * 6 + [1] * 6, np.int32))
    paths = author_asset(fits, _patch(), regions, tmp_path / "asset")
    stage = Usd.Stage.Open(str(paths.asset))
    back = {f.name: f for f, _ in read_profiles(stage).values()}
    for fit in fits:
        got = back[fit.name]
        assert got.variances_mm2.tolist() == fit.variances_mm2.tolist()
        assert got.weights.tolist() == fit.weights.tolist()
        assert got.error.tolist() == fit.error.tolist()
        assert got.status == fit.status and got.solver == fit.solver


def test_asset_structure(fit_files: Path, tmp_path: Path) -> None:
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("forehead", "cheek"), np.array([0] * 6 + [1] * 6, np.int32))
    paths = author_asset(fits, _patch(), regions, tmp_path / "a", name="Jane")
    assert sorted(p.name for p in (tmp_path / "a").iterdir()) == \
        ["asset.usda", "geo.usdc", "look.mtlx", "look.usda"]
    stage = Usd.Stage.Open(str(paths.asset))
    root = stage.GetDefaultPrim()
    assert root.GetPath() == "/Jane" and Usd.ModelAPI(root).GetKind() == Kind.Tokens.component
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.001
    assert UsdGeom.GetStageUpAxis(stage) == "Y"
    mesh = stage.GetPrimAtPath("/Jane/Geom/Mesh")
    assert "SkinProfileRegionsAPI" in mesh.GetAppliedSchemas()
    targets = mesh.GetRelationship("skin:profiles").GetTargets()
    assert [t.name for t in targets] == ["forehead", "cheek"]
    # AOUSD asset structure: geometry behind a payload, the root at the asset's origin
    # (bounds' bottom centre) with the scan's placement as the root's transform
    # with the payload unloaded no geometry is defined: the look's bindings of the
    # region subsets (the skinLook variant) are overs without a type
    unloaded = Usd.Stage.Open(str(paths.asset), Usd.Stage.LoadNone)
    below = list(Usd.PrimRange(unloaded.GetPrimAtPath("/Jane/Geom"),
                               Usd.PrimAllPrimsPredicate))
    assert below and not any(p.IsDefined() for p in below)
    assert not unloaded.GetPrimAtPath("/Jane/Geom/Mesh").IsDefined()
    local = np.asarray(UsdGeom.Mesh(mesh).GetPointsAttr().Get())
    assert abs(local[:, 1].min()) < 1e-4
    np.testing.assert_allclose((local.min(0) + local.max(0))[[0, 2]] / 2, 0, atol=1e-4)
    world = UsdGeom.Xformable(mesh).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    np.testing.assert_allclose([world.Transform(Gf.Vec3d(*map(float, p)))
                                for p in local[:3]], _patch().points[:3], atol=1e-3)
    report = validate_file(paths.asset)
    assert not report.failed(strict=False)
    assert all(p.severity == NOT_APPLICABLE for p in report.problems)


def test_an_unloaded_asset_has_the_loaded_ones_box(fit_files: Path, tmp_path: Path) -> None:
    """Pixar's model guidelines: a component carries extentsHint, so that a set with the
    payload unloaded still knows its size. USD's own bounding-box cache, reading the
    hint with the payload unloaded, gives the box it computes from the loaded mesh."""
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("forehead", "cheek"), np.array([0] * 6 + [1] * 6, np.int32))
    paths = author_asset(fits, _patch(), regions, tmp_path / "a", name="Jane")
    purposes = [UsdGeom.Tokens.default_]

    def world_box(load: Any, hint: bool) -> Any:
        stage = Usd.Stage.Open(str(paths.asset), load)
        cache = UsdGeom.BBoxCache(Usd.TimeCode.Default(), purposes, useExtentsHint=hint)
        return cache.ComputeWorldBound(stage.GetDefaultPrim()).ComputeAlignedRange()

    unloaded = world_box(Usd.Stage.LoadNone, True)
    loaded = world_box(Usd.Stage.LoadAll, False)
    assert not unloaded.IsEmpty()
    np.testing.assert_allclose(unloaded.GetMin(), loaded.GetMin(), atol=1e-3)
    np.testing.assert_allclose(unloaded.GetMax(), loaded.GetMax(), atol=1e-3)
    np.testing.assert_allclose(loaded.GetMin(), _patch().points.min(0), atol=1e-3)


def test_landmark_regions_cover_the_face_scan() -> None:
    mesh = load_mesh(pymeshlab_face_scan())
    regions = assign_regions_from_landmarks(mesh, read_landmarks(SAMPLE_LANDMARKS))
    assert set(regions.names) == {"forehead", "lips", "chin", "cheekbone", "cheek", "nose"}
    counts = np.bincount(regions.face_region, minlength=6)
    assert np.all(counts > 1000)
    np.testing.assert_allclose(regions.vertex_weights.sum(axis=1), 1.0, atol=1e-5)


def test_missing_fit_for_a_region(fit_files: Path, tmp_path: Path) -> None:
    fits = [read_fit_json(fit_files / "forehead.json")]
    regions = RegionAssignment(("forehead", "nose"), np.zeros(12, np.int32))
    with pytest.raises(InputError, match=r"no fit for region\(s\) \['nose'\]"):
        author_asset(fits, _patch(), regions, tmp_path / "x")
    assert not (tmp_path / "x").exists()


def test_bad_mesh_inputs(tmp_path: Path) -> None:
    bad = tmp_path / "bad.obj"
    bad.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    with pytest.raises(InputError):
        load_mesh(bad)
    with pytest.raises(InputError, match="no such mesh"):
        load_mesh(tmp_path / "missing.ply")


def test_author_cli_never_touches_the_input_layer(fit_files: Path, tmp_path: Path) -> None:
    src = tmp_path / "in" / "geo.usda"
    stage = Usd.Stage.CreateNew(str(src))
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    m = UsdGeom.Mesh.Define(stage, "/Head")
    patch = _patch()
    m.CreatePointsAttr(patch.points.tolist())
    m.CreateFaceVertexCountsAttr(patch.face_counts.tolist())
    m.CreateFaceVertexIndicesAttr(patch.face_indices.tolist())
    pv = UsdGeom.PrimvarsAPI(m).CreatePrimvar("region", Sdf.ValueTypeNames.IntArray,
                                             UsdGeom.Tokens.uniform)
    pv.Set([0] * 6 + [1] * 6)
    stage.Save()
    before = src.read_bytes()
    out = tmp_path / "asset"
    assert main(["author", "--fits", str(fit_files), "--mesh", str(src), "--region-primvar",
                 "region", "--region-names", "forehead,cheek", "-o", str(out)]) == 0
    assert src.read_bytes() == before
    assert main(["validate", str(out / "asset.usda")]) == 0
    stage = Usd.Stage.Open(str(out / "asset.usda"))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 0.01


def test_inspect_prints_and_plots(fit_files: Path, tmp_path: Path,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("forehead", "cheek"), np.array([0] * 6 + [1] * 6, np.int32))
    paths = author_asset(fits, _patch(), regions, tmp_path / "a")
    png = tmp_path / "p.png"
    assert main(["inspect", str(paths.asset), "--plot", str(png), "--log-radius"]) == 0
    out = capsys.readouterr().out
    assert "region=forehead" in out and "eq. 2c error" in out
    # the medium other renderers get, as authored on the profile prim
    stage = Usd.Stage.Open(str(paths.asset))
    mfp = stage.GetPrimAtPath("/Face/Looks/Profiles/forehead").GetAttribute(
        "medium:meanFreePathMm").Get()
    assert "medium (OpenPBR subsurface)" in out
    assert f"mean free path mm: R={mfp[0]:.4g}" in out
    assert (tmp_path / "p_forehead.png").stat().st_size > 10000
    assert main(["inspect", str(paths.asset), "--prim", "/Nope"]) == 2


def test_env_prints_plugin_path(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["env"]) == 0
    line = capsys.readouterr().out
    assert line.startswith("export PXR_PLUGINPATH_NAME=") and "schemas" in line


def test_usdview_plugin_info_names_a_real_container() -> None:
    import skinpipe.usdview_plugin as plugin

    info = json.loads((Path(plugin.__file__).parent / "plugInfo.json").read_text())
    types = info["Plugins"][0]["Info"]["Types"]
    (name,) = types
    assert name == "skinpipe.usdview_plugin.SkinPluginContainer"
    assert hasattr(plugin, "SkinPluginContainer") and hasattr(plugin, "plot_selected_profiles")


def test_inspect_shows_what_a_shadow_edge_shows(demo_run: tuple[Path, str, str],
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """Beside eq. 2c, the edge figures against the measured samples the asset carries:
    the spread error, the 10-90% widths fitted and measured, the light in the shadow."""
    asset = demo_run[0] / "asset" / "asset.usda"
    assert main(["inspect", str(asset), "--prim", "/Face/Looks/Profiles/cheek"]) == 0
    out = capsys.readouterr().out
    assert "shadow edge: spread error R=" in out
    widths = out.split("10-90% edge width mm (fit/measured): ")[1].splitlines()[0].split()
    for item in widths:  # R=4.06/4.06 ...
        fitted, measured = (float(x) for x in item.split("=")[1].split("/"))
        assert abs(fitted / measured - 1) < 0.05, out
    assert "light in the shadow (fit/measured): R=" in out
