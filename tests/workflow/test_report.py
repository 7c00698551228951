"""Error-against-run-time report: Pareto front, the render trade-off on a patch, and
the one-page report gathering every stage."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.workflow.report import (
    lighting_tradeoff,
    pareto_front,
    render_tradeoff,
    write_lighting_report,
    write_render_report,
    write_report_page,
)
from tests.render_scenes import deon_fit, distant_down, patch_asset, scene_over, top_camera


def test_pareto_front_keeps_only_undominated_points() -> None:
    # (seconds, error): (2, 0.5) is beaten by (1, 0.4); (3, 0.1) and (1, 0.4) are not
    points = [(1.0, 0.4), (2.0, 0.5), (3.0, 0.1), (4.0, 0.1), (0.5, 0.9)]
    assert sorted(pareto_front(points)) == [0, 2, 4]
    assert pareto_front([]) == []


def _patch_under_plate(tmp: Path, light: Callable[[Any], None]) -> Path:
    """A 40 mm patch seen from above, ``light`` (a function of the stage) over it, and a
    plate 5 mm up shading its x < 0 half."""
    from pxr import Gf, UsdGeom

    asset = patch_asset(tmp / "asset", [deon_fit()], n=24)

    def build(stage) -> None:
        top_camera(stage)
        light(stage)
        plate = UsdGeom.Mesh.Define(stage, "/Plate")
        plate.CreatePointsAttr([(-30, -30, 5), (0, -30, 5), (0, 30, 5), (-30, 30, 5)])
        plate.CreateFaceVertexCountsAttr([4])
        plate.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        plate.CreateExtentAttr([Gf.Vec3f(-30, -30, 5), Gf.Vec3f(0, 30, 5)])

    return scene_over(asset, tmp / "scene.usda", build)


@pytest.fixture(scope="module")
def half_shadowed_patch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The patch lit from above: the diffused light crossing the shadow edge is what the
    report measures."""
    return _patch_under_plate(tmp_path_factory.mktemp("report"),
                              lambda stage: distant_down(stage, intensity=3.0))


def test_render_tradeoff_rows_and_page(half_shadowed_patch: Path, tmp_path: Path) -> None:
    rows = render_tradeoff(half_shadowed_patch, sizes=(64, 128), grids=(0, 4),
                           light_samples=1, points=150, blurs=("recursive", "gather"))
    assert len(rows) == 8
    assert {(r["texture_size"], r["variance_grid"], r["blur"]) for r in rows} == {
        (s, g, b) for s in (64, 128) for g in (0, 4) for b in ("recursive", "gather")}
    for r in rows:
        assert math.isfinite(r["error_max"]) and 0 <= r["error_max"] < 0.5
        assert r["energy_ratio"] == pytest.approx(1.0, abs=0.02)
    by = {(r["texture_size"], r["variance_grid"], r["blur"]): r for r in rows}
    for size in (64, 128):
        for grid in (0, 4):
            rec, gat = by[size, grid, "recursive"], by[size, grid, "gather"]
            # both blurs see the same light: their errors agree within a tenth
            assert rec["error_max"] == pytest.approx(gat["error_max"], rel=0.1)
            assert rec["error_median_point"] < 0.2
    doc = write_render_report(rows, tmp_path, default=(128, 4, "recursive"))
    assert len(doc["default"]["on_pareto_front"]) == 1
    assert any(r["pareto"] for r in doc["rows"])
    page = write_report_page(tmp_path)
    text = page.read_text()
    assert "## Render" in text and "render_tradeoff.png" in text
    assert "## Fit" not in text  # only what was measured is on the page
    assert text.count("| 128 |") == 4
    assert (tmp_path / "render_tradeoff.png").stat().st_size > 0
    saved = json.loads((tmp_path / "render_tradeoff.json").read_text())
    assert saved["default"]["blur"] == "recursive"


@pytest.fixture(scope="module")
def sphere_lit_patch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The patch under a sphere light: a soft shadow."""
    from pxr import Gf, UsdGeom, UsdLux

    def sphere(stage) -> None:
        light = UsdLux.SphereLight.Define(stage, "/Key")
        light.CreateRadiusAttr(8.0)
        light.CreateIntensityAttr(3.0)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(0, 0, 60))

    return _patch_under_plate(tmp_path_factory.mktemp("lighting"), sphere)


def test_lighting_tradeoff_rows_and_page(sphere_lit_patch: Path, tmp_path: Path) -> None:
    rows = lighting_tradeoff(sphere_lit_patch, texture_size=128, light_samples=(4, 16),
                             reference_samples=256)
    assert {(r["light_samples"], r["shadow_sampling"]) for r in rows} == {
        (n, m) for n in (4, 16) for m in ("adaptive", "interleaved", "full")}
    by = {(r["light_samples"], r["shadow_sampling"]): r for r in rows}
    for mode in ("adaptive", "interleaved", "full"):
        assert 0 < by[16, mode]["error_max"] < by[4, mode]["error_max"] < 0.2
    # adaptive: full sampling's error (the same strata in the penumbra) for fewer rays
    assert by[16, "adaptive"]["error_max"] <= 1.05 * by[16, "full"]["error_max"]
    assert by[16, "adaptive"]["rays_per_texel"] < 0.6 * by[16, "full"]["rays_per_texel"]
    assert by[16, "interleaved"]["rays_per_texel"] < by[16, "adaptive"]["rays_per_texel"]
    write_lighting_report(rows, tmp_path, default=(16, "interleaved", "sobol"))
    text = write_report_page(tmp_path).read_text()
    assert "## Irradiance" in text and text.count("| 128 | 16 |") == 3
    assert (tmp_path / "lighting_tradeoff.png").stat().st_size > 0


def test_report_page_needs_a_measured_stage(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"no \*_tradeoff\.json"):
        write_report_page(tmp_path)
    assert not (tmp_path / "report.md").exists()


def test_report_cli_fit_writes_the_page(tmp_path: Path, capsys) -> None:
    from skinpipe.cli import main
    from skinpipe.profile.io import write_profile_csv
    from skinpipe.profile.models import sum_of_gaussians
    from skinpipe.profile.reference_data import DEON_2007_SKIN
    from skinpipe.profile.types import MeasuredProfile

    r = np.linspace(0.0, 4.0, 120)
    csv = tmp_path / "deon.csv"
    write_profile_csv(csv, MeasuredProfile(r, sum_of_gaussians(
        DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r), name="deon"))
    out = tmp_path / "report"
    assert main(["report", "fit", str(csv), "--k", "2:3", "-o", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "## Fit" in text and "fit_tradeoff.png" in text
    assert "| eq. 2c | edge | width | shadow light |" in text
    rows = json.loads((out / "fit_tradeoff.json").read_text())["rows"]
    assert all(len(r["edge_error"]) == 3 and len(r["shadow_light_ratio"]) == 3 for r in rows)
    assert "ga+ipopt, k = 6" in text  # default not measured: the page says so
    assert "not among the measured rows" in text
    assert main(["report", "render", "-o", str(out)]) == 2  # no scene given
    assert "needs exactly one SCENE" in capsys.readouterr().err


@pytest.mark.parametrize(("period", "rtol"), [("2", 0.01), ("auto", 0.02)])
def test_render_cli_adaptive_equals_full_sampling_in_the_image(
        sphere_lit_patch: Path, tmp_path: Path, period: str, rtol: float) -> None:
    """`skinpipe render --shadow-sampling adaptive`: the irradiance AOV of full sampling
    (the same strata where the rays disagreed, 0 or 1 elsewhere; the unshadowed light
    from a texel's share of them), fewer rays, and the penumbra in render.json. At 48
    pixels the 128 texture is 6 texels a pixel: auto takes period 4, whose texels
    estimate the unshadowed light from one of the 16 samples (measured: 0.24% at worst
    at period 2, interleaved 4.7%; 1.15% at period 4)."""
    import OpenImageIO as oiio

    from skinpipe.cli import main

    docs, images = {}, {}
    for mode in ("adaptive", "full"):
        out = tmp_path / mode
        assert main(["render", str(sphere_lit_patch), "--resolution", "48x48",
                     "--texture-size", "128", "--aovs", "beauty,irradiance",
                     "--shadow-sampling", mode, "--interleave-period", period,
                     "-o", str(out)]) == 0
        docs[mode] = json.loads((out / "render.json").read_text())
        images[mode] = oiio.ImageBuf(str(out / "scene.exr")).get_pixels(oiio.FLOAT)
    measures = {m: docs[m]["frames"][0]["measures"]["irradiance"] for m in docs}
    assert measures["adaptive"]["interleave_period"] == (2 if period == "2" else 4)
    assert measures["adaptive"]["rays"] < 0.6 * measures["full"]["rays"]
    assert 0 < measures["adaptive"]["penumbra_texels"]["/Key"] < 0.5 * 128 * 128
    np.testing.assert_allclose(images["adaptive"], images["full"], rtol=rtol, atol=1e-4)


@pytest.mark.parametrize("option", [["--lighting-size", "5"], ["--light-samples", "4,0"],
                                    ["--shadow-sampling", "some"], ["--sizes", "64,x"],
                                    ["--light-sequences", "halton"], ["--blurs", "box"]])
def test_report_render_refuses_bad_axes_before_measuring(
        option: list[str], sphere_lit_patch: Path, tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    from skinpipe.cli import main

    out = tmp_path / "report"
    assert main(["report", "render", str(sphere_lit_patch), *option, "-o", str(out)]) == 2
    assert not out.exists()
    assert option[0] in capsys.readouterr().err
