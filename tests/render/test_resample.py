"""Images resampled to a texture's texel centres, against lookups and OpenImageIO."""

from __future__ import annotations

import numpy as np

from pipeline.render.renderer import bilinear
from pipeline.render.resample import ResampledTexture, resample_bilinear


def test_resample_bilinear_equals_bilinear_lookups_at_texel_centres() -> None:
    rng = np.random.default_rng(2)
    for shape, size in (((37, 50, 3), 16), ((1, 5, 3), 8), ((64, 64, 3), 64),
                        ((20, 20, 3), 51)):
        image = rng.random(shape).astype(np.float32)
        centres = (np.arange(size) + 0.5) / size
        uu, vv = np.meshgrid(centres, centres)
        want = bilinear(image, np.stack([uu.ravel(), vv.ravel()], axis=1))
        np.testing.assert_allclose(resample_bilinear(image, size),
                                   want.reshape(size, size, 3), atol=1e-5)  # float32 uv


def test_resample_bilinear_equals_openimageio_at_texel_centres() -> None:
    """The albedo's resample against OpenImageIO's own bilinear lookup (interppixel_NDC,
    edges clamped) at each texel centre, up and down in size: within float32 rounding
    of the positions (measured 1.2e-6 at most, on values in [0, 1])."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(5)
    for (h, w), size in (((5, 7), 16), ((37, 50), 16), ((20, 20), 51)):
        image = rng.random((h, w, 3)).astype(np.float32)
        buf = oiio.ImageBuf(oiio.ImageSpec(w, h, 3, oiio.FLOAT))
        buf.set_pixels(oiio.ROI(), image)
        centres = (np.arange(size) + 0.5) / size
        want = np.array([[buf.interppixel_NDC(float(u), float(v), "clamp") for u in centres]
                         for v in centres], np.float32)
        np.testing.assert_allclose(resample_bilinear(image, size), want, atol=3e-6)


def test_a_resampled_texture_is_the_resample_bit_for_bit_in_bands_and_texels() -> None:
    # ResampledTexture (the renderer's albedo) made a band of rows or a set of texels at
    # a time: resample_bilinear's values clipped at 0, bit for bit, up, down and the
    # same size; a 1 x 1 source (a constant albedo) is its value everywhere, unclipped;
    # bilinear lookups in it are those in the whole map
    rng = np.random.default_rng(7)
    for shape, size in (((37, 50, 3), 16), ((1, 5, 3), 8), ((64, 64, 3), 64),
                        ((20, 20, 3), 51), ((128, 96, 3), 512)):
        image = rng.random(shape).astype(np.float32) - np.float32(0.1)
        whole = np.clip(resample_bilinear(image, size), 0, None)
        tex = ResampledTexture(image, size)
        assert tex.shape == whole.shape
        np.testing.assert_array_equal(np.asarray(tex), whole)
        np.testing.assert_array_equal(
            np.concatenate([tex[y:y + 7] for y in range(0, size, 7)]), whole)
        flat = rng.integers(0, size * size, 3000)
        np.testing.assert_array_equal(tex.texels(flat), whole.reshape(-1, 3)[flat])
        uv = rng.random((500, 2))
        np.testing.assert_array_equal(bilinear(tex, uv), bilinear(whole, uv))
    constant = ResampledTexture(np.array([[[-0.5, 0.25, np.inf]]], np.float32), 9, low=None)
    np.testing.assert_array_equal(constant[2:5], np.broadcast_to([-0.5, 0.25, np.inf],
                                                                   (3, 9, 3)))
    np.testing.assert_array_equal(constant.texels(np.array([0, 80])),
                                  [[-0.5, 0.25, np.inf]] * 2)
