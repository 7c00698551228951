"""Fixtures the render tests share."""

from __future__ import annotations

from pathlib import Path

import pytest

from ..render_scenes import deon_fit, distant_down, patch_asset, scene_over, top_camera


@pytest.fixture
def lit_patch(tmp_path: Path) -> Path:
    """A flat patch with d'Eon's profile under a camera straight above and a distant
    light straight down (intensity 2)."""
    asset = patch_asset(tmp_path / "asset", [deon_fit()])

    def build(stage) -> None:
        top_camera(stage)
        distant_down(stage, intensity=2.0)

    return scene_over(asset, tmp_path / "scene.usda", build)
