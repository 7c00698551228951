"""Images as other tools read them: OpenImageIO reads back ACEScg chromaticities
(checked against colour-science's definition of the space) and textures that are tiled,
MIP-mapped and half float."""

from __future__ import annotations

from pathlib import Path

import colour
import numpy as np
import OpenImageIO as oiio

from skinpipe.imageio import ACESCG, read_image, write_exr, write_texture


def _acescg_chromaticities() -> list[float]:
    space = colour.models.RGB_COLOURSPACE_ACESCG
    return [*np.asarray(space.primaries).ravel(), *space.whitepoint]


def test_exr_names_acescg_in_openexr_terms(tmp_path: Path) -> None:
    path = write_exr(tmp_path / "a.exr", np.full((4, 5, 3), 0.25, np.float32), ACESCG)
    spec = oiio.ImageInput.open(str(path)).spec()
    np.testing.assert_allclose(spec.getattribute("chromaticities"), _acescg_chromaticities(),
                               atol=1e-4)
    assert spec.getattribute("oiio:ColorSpace") == ACESCG


def test_texture_is_tiled_mipmapped_half(tmp_path: Path) -> None:
    img = np.random.default_rng(0).random((64, 128, 3)).astype(np.float32)
    path = write_texture(tmp_path / "t.exr", img)
    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    assert (spec.tile_width, spec.tile_height) == (64, 64) and spec.format == "half"
    np.testing.assert_allclose(spec.getattribute("chromaticities"), _acescg_chromaticities(),
                               atol=1e-4)
    levels = 0
    while inp.seek_subimage(0, levels):
        levels += 1
    inp.close()
    assert levels == 8  # 128 x 64 down to 1 x 1
    back = read_image(path).pixels[..., :3]
    np.testing.assert_allclose(back, img, atol=1e-3)  # half float: 11 bits
    assert not list(tmp_path.glob(".*"))  # written through a temporary, renamed


def test_ldr_images_read_back_as_their_code_values(tmp_path: Path) -> None:
    """8-bit PNG (written at zlib's fastest level) and 16-bit TIFF: OpenImageIO reads back
    every pixel's rounded code value; compression loses nothing. (Opaque: OpenImageIO
    takes colour with alpha as premultiplied and stores it divided by alpha.)"""
    from skinpipe.imageio import write_ldr

    pixels = np.random.default_rng(3).random((37, 61, 4))
    pixels[..., 3] = 1.0
    for suffix, bits, dtype in ((".png", 8, oiio.UINT8), (".tif", 16, oiio.UINT16)):
        path = write_ldr(tmp_path / f"a{suffix}", pixels, bits)
        got = oiio.ImageBuf(str(path)).get_pixels(dtype)
        want = np.rint(pixels * ((1 << bits) - 1))
        np.testing.assert_array_equal(got.astype(np.int64), want.astype(np.int64))
    spec = oiio.ImageInput.open(str(tmp_path / "a.png")).spec()
    assert (spec.width, spec.height, spec.nchannels) == (61, 37, 4)
