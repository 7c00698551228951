"""Error-against-run-time report: Pareto front, the render trade-off on a patch, and
the one-page report gathering every stage."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from pipeline.errors import InputError
from pipeline.workflow.report import (
    pareto_front,
    render_tradeoff,
    write_render_report,
    write_report_page,
)
from tests.render_scenes import deon_fit, distant_down, patch_asset, scene_over, top_camera


def test_pareto_front_keeps_only_undominated_points() -> None:
    # (seconds, error): (2, 0.5) is beaten by (1, 0.4); (3, 0.1) and (1, 0.4) are not
    points = [(1.0, 0.4), (2.0, 0.5), (3.0, 0.1), (4.0, 0.1), (0.5, 0.9)]
    assert sorted(pareto_front(points)) == [0, 2, 4]
    assert pareto_front([]) == []


@pytest.fixture(scope="module")
def half_shadowed_patch(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 40 mm patch lit from above with a plate shading half of it: the diffused
    light crossing the shadow edge is what the report measures."""
    from pxr import Gf, UsdGeom

    tmp = tmp_path_factory.mktemp("report")
    asset = patch_asset(tmp / "asset", [deon_fit()], n=24)

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage, intensity=3.0)
        plate = UsdGeom.Mesh.Define(stage, "/Plate")
        plate.CreatePointsAttr([(-30, -30, 5), (0, -30, 5), (0, 30, 5), (-30, 30, 5)])
        plate.CreateFaceVertexCountsAttr([4])
        plate.CreateFaceVertexIndicesAttr([0, 1, 2, 3])
        plate.CreateExtentAttr([Gf.Vec3f(-30, -30, 5), Gf.Vec3f(0, 30, 5)])

    return scene_over(asset, tmp / "scene.usda", build)


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


def test_report_page_needs_a_measured_stage(tmp_path: Path) -> None:
    with pytest.raises(InputError, match=r"no \*_tradeoff\.json"):
        write_report_page(tmp_path)
    assert not (tmp_path / "report.md").exists()


def test_report_cli_fit_writes_the_page(tmp_path: Path, capsys) -> None:
    from pipeline.cli import main
    from pipeline.profile.fit import MeasuredProfile
    from pipeline.profile.io import write_profile_csv
    from pipeline.profile.models import sum_of_gaussians
    from pipeline.profile.reference_data import DEON_2007_SKIN

    r = np.linspace(0.0, 4.0, 120)
    csv = tmp_path / "deon.csv"
    write_profile_csv(csv, MeasuredProfile(r, sum_of_gaussians(
        DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r), name="deon"))
    out = tmp_path / "report"
    assert main(["report", "fit", str(csv), "--k", "2:3", "-o", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "## Fit" in text and "fit_tradeoff.png" in text
    assert "ga+ipopt, k = 6" in text  # default not measured: the page says so
    assert "not among the measured rows" in text
    assert main(["report", "render", "-o", str(out)]) == 2  # no scene given
    assert "needs exactly one SCENE" in capsys.readouterr().err
