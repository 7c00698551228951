"""The skin material as MaterialX, checked by the ``materialx`` package itself: the
.mtlx document passes MaterialX's validate(), its OpenPBR subsurface inputs follow the
fits, and the USD network in the mtlx render context matches MaterialX's node
definitions (and fails where it does not)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import MaterialX as mx
import numpy as np
import pytest
from pxr import Sdf, Usd, UsdShade

from skinpipe.profile.io import read_fit_json
from skinpipe.usd.author import MTLX_NAME, RegionAssignment, author_asset
from skinpipe.usd.materialx import (
    document_problems,
    mtlx_document,
    network_problems,
    read_openpbr_inputs,
    write_mtlx_document,
)

from .test_author import _patch, fit_files  # noqa: F401  (fixture)


@pytest.fixture
def asset(fit_files: Path, tmp_path: Path) -> tuple[Path, list]:  # noqa: F811
    fits = [read_fit_json(p) for p in sorted(fit_files.glob("*.json"))]
    regions = RegionAssignment(("forehead", "cheek"), np.array([0] * 6 + [1] * 6, np.int32))
    return author_asset(fits, _patch(), regions, tmp_path / "a").asset, fits


def _document_with_library(path: Path) -> Any:
    doc = mx.createDocument()
    mx.readFromXmlFile(doc, str(path))
    lib = mx.createDocument()
    mx.loadLibraries(mx.getDefaultDataLibraryFolders(), mx.getDefaultDataSearchPath(), lib)
    doc.importLibrary(lib)
    return doc


def test_mtlx_document_passes_materialx_validate(asset: tuple[Path, list]) -> None:
    doc = _document_with_library(asset[0].parent / MTLX_NAME)
    ok, message = doc.validate()
    assert ok, message
    assert doc.getColorSpace() == "acescg"
    material = doc.getNode("SkinMaterial")
    assert material.getCategory() == "surfacematerial"
    shader = material.getInput("surfaceshader").getConnectedNode()
    assert shader.getCategory() == "open_pbr_surface"


def test_openpbr_subsurface_is_each_region_medium(asset: tuple[Path, list]) -> None:
    """Each region's OpenPBR: its medium's mean free path as radius times scale (scene
    units: mm here), its subsurface colour, and the two regions differ."""
    path, _ = asset
    stage = Usd.Stage.Open(str(path))
    seen = []
    for region in ("forehead", "cheek"):
        inputs = read_openpbr_inputs(path.parent / MTLX_NAME, f"OpenPBR_{region}")
        prim = stage.GetPrimAtPath(f"/Face/Looks/Profiles/{region}")
        mfp = np.array(prim.GetAttribute("medium:meanFreePathMm").Get())
        assert inputs["subsurface_radius"] == pytest.approx(mfp.max(), rel=1e-5)
        np.testing.assert_allclose(inputs["subsurface_radius_scale"] * inputs[
            "subsurface_radius"], mfp, rtol=1e-5)
        np.testing.assert_allclose(inputs["subsurface_color"],
                                   prim.GetAttribute("medium:subsurfaceColor").Get(), rtol=1e-5)
        assert inputs["subsurface_weight"] == 1.0
        seen.append(inputs["subsurface_radius"])
    assert seen[0] != pytest.approx(seen[1], rel=1e-3)


@pytest.mark.parametrize("generator", ["Glsl", "Osl", "Mdl"])
def test_every_material_of_the_document_generates_a_shader(asset: tuple[Path, list],
                                                           generator: str) -> None:
    """MaterialX's own shader generators (GLSL, OSL, MDL) take every material of
    look.mtlx, textured as the albedo bake writes it."""
    import importlib

    gen_shader = importlib.import_module("MaterialX.PyMaterialXGenShader")
    module = importlib.import_module(f"MaterialX.PyMaterialXGen{generator}")
    values = {name: read_openpbr_inputs(asset[0].parent / MTLX_NAME, shader) for name, shader
              in (("SkinMaterial", "OpenPBR"), ("forehead", "OpenPBR_forehead"),
                  ("cheek", "OpenPBR_cheek"))}
    doc = mtlx_document(values, "albedo.exr")
    gen = getattr(module, f"{generator}ShaderGenerator").create()
    context = gen_shader.GenContext(gen)
    context.registerSourceCodeSearchPath(mx.getDefaultDataSearchPath())
    for name in values:
        shader = doc.getNode(name).getInput("surfaceshader").getConnectedNode()
        code = gen.generate(name, shader, context).getSourceCode(gen_shader.PIXEL_STAGE)
        assert len(code) > 1000


def test_usd_network_matches_materialx_definitions(asset: tuple[Path, list]) -> None:
    stage = Usd.Stage.Open(Usd.Stage.Open(str(asset[0])).Flatten())  # one layer to edit
    material = UsdShade.Material(stage.GetPrimAtPath("/Face/Looks/SkinMaterial"))
    source, output, _ = material.ComputeSurfaceSource("mtlx")
    assert source.GetShaderId() == "ND_open_pbr_surface_surfaceshader" and output == "out"
    assert network_problems(source.GetPrim()) == []
    # a float3 where the definition says color3 is caught
    prim = source.GetPrim()
    prim.RemoveProperty("inputs:base_color")
    prim.CreateAttribute("inputs:base_color", Sdf.ValueTypeNames.Float3).Set((0.5, 0.4, 0.3))
    prim.CreateAttribute("inputs:no_such_port", Sdf.ValueTypeNames.Float).Set(1.0)
    problems = [m for m, _ in network_problems(prim)]
    assert any("color3" in m and "base_color" in m for m in problems)
    assert any("no_such_port" in m for m in problems)


def test_textured_document_and_its_element_check_agree_with_validate(
        asset: tuple[Path, list], tmp_path: Path) -> None:
    """mtlx_document checks each of its own elements, not the library again: what it
    writes passes the whole document's validate(), and a wrong connection it refuses."""
    values = {"SkinMaterial": read_openpbr_inputs(asset[0].parent / MTLX_NAME)}
    path = write_mtlx_document(tmp_path / "textured.mtlx", mtlx_document(values, "albedo.exr"))
    ok, message = _document_with_library(path).validate()
    assert ok, message
    doc = mtlx_document(values, "albedo.exr")
    doc.getNode("MtlxAlbedo").setType("float")  # color3 inputs now read a float
    broken = write_mtlx_document(tmp_path / "broken.mtlx", doc)
    ok, message = _document_with_library(broken).validate()
    assert not ok and "Mismatched types" in message
    assert any("Mismatched types" in p for p in document_problems(doc))
