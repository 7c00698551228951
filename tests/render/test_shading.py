"""The shading helpers that read the scene's textures."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import OpenImageIO as oiio
import pytest

from skinpipe.render.scene import Albedo
from skinpipe.render.shading import albedo_image, mean_albedo

WORKING = "lin_ap1_scene"


def _write(path: Path, pixels: np.ndarray, tiled_mips: bool = False) -> Path:
    h, w, c = pixels.shape
    fmt = oiio.FLOAT if pixels.dtype == np.float32 else oiio.UINT8
    buf = oiio.ImageBuf(oiio.ImageSpec(w, h, c, fmt))
    buf.set_pixels(oiio.ROI(), pixels)
    if tiled_mips:  # as maketx makes a renderer's texture
        assert oiio.ImageBufAlgo.make_texture(oiio.MakeTxTexture, buf, str(path))
    else:
        assert buf.write(str(path))
    return path


def _mesh(texture: Path, colorspace: str | None = None) -> SimpleNamespace:
    return SimpleNamespace(albedo=Albedo((0.5, 0.5, 0.5), texture, colorspace))


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_the_mean_albedo_is_the_mean_of_the_decoded_image(tmp_path: Path,
                                                          channels: int) -> None:
    px = (np.random.default_rng(0).random((300, 200, channels)) * 255).astype(np.uint8)
    mesh = _mesh(_write(tmp_path / "a.png", px))
    image, _ = albedo_image(mesh, WORKING)  # type: ignore[arg-type]
    np.testing.assert_allclose(mean_albedo(mesh, WORKING),  # type: ignore[arg-type]
                               image.reshape(-1, 3).mean(axis=0), rtol=1e-4)


def test_a_mip_mapped_texture_gives_its_mean_from_the_coarsest_level(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    px = rng.random((512, 512, 3)).astype(np.float32) * np.float32([0.8, 0.4, 0.2])
    mesh = _mesh(_write(tmp_path / "a.exr", px, tiled_mips=True))
    np.testing.assert_allclose(mean_albedo(mesh, WORKING),  # type: ignore[arg-type]
                               px.reshape(-1, 3).mean(axis=0), rtol=2e-3)


def test_a_constant_albedo_is_its_own_mean() -> None:
    mesh = SimpleNamespace(albedo=Albedo((0.1, 0.2, 0.3)))
    np.testing.assert_allclose(mean_albedo(mesh, WORKING), [0.1, 0.2, 0.3])  # type: ignore[arg-type]
