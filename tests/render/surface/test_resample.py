"""Images resampled to a texture's texel centres, against lookups and OpenImageIO."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.render.shading import albedo_texels, albedo_texture, bilinear, bilinear_of
from skinpipe.render.surface.resample import (
    resample_bilinear,
    resampled_texels,
    take_rows,
    times_resampled_power,
)


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


def test_resampled_texels_are_the_resampled_images_texels() -> None:
    """Texels of the resample made one by one (resampled_texels) are the whole image's
    (resample_bilinear), bit for bit: up, down, the same size and a 1 x 1 constant."""
    rng = np.random.default_rng(3)
    for (h, w), size in (((37, 50), 64), ((64, 64), 64), ((90, 70), 40), ((1, 1), 16),
                         ((2, 300), 33)):
        image = (rng.random((h, w, 3)) * 1.2 - 0.1).astype(np.float32)
        index = rng.integers(0, size * size, 4000)
        got = resampled_texels(image, size, index)
        assert got.dtype == np.float32
        np.testing.assert_array_equal(got, resample_bilinear(image, size).reshape(-1, 3)[index])


def test_take_rows_is_fancy_indexing() -> None:
    """take_rows against numpy's fancy indexing: contiguous rows, a view of a wider
    array's first columns (the irradiance beside the visibility planes), one column of
    it, 1-D values; repeated and last indices, none at all."""
    rng = np.random.default_rng(4)
    planes = rng.random((50 * 40, 5)).astype(np.float32)
    for rows in (planes, planes[:, :3], planes[:, 3], planes[:, 3:4],
                 np.ascontiguousarray(planes[:, 3])):
        for index in (rng.integers(0, rows.shape[0], 3000),
                      np.array([rows.shape[0] - 1, 0, 0]), np.array([], np.int64)):
            got = take_rows(rows, index)
            assert got.dtype == rows.dtype and got.shape == rows[index].shape
            np.testing.assert_array_equal(got, rows[index])


def test_albedo_lookups_without_the_map_are_the_maps() -> None:
    """The shading's albedo at texture coordinates made from the albedo's own image
    (bilinear_of albedo_texels) is the bilinear lookup in its map (albedo_texture), bit
    for bit, values below 0 clipped as the map clips them; and the map's texels are
    OpenImageIO's bilinear lookups of the image at the texel centres (interppixel_NDC,
    within float32 rounding of the positions: 3.8e-6 at most measured), clipped."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(11)
    for (h, w), size in (((37, 50), 64), ((64, 64), 64), ((90, 70), 40)):
        image = (rng.random((h, w, 3)) * 1.2 - 0.1).astype(np.float32)
        uv = rng.random((5000, 2))
        uv[:10] = [[0, 0], [1, 1], [0, 1], [1, 0], [0.5, 0], [0, 0.5], [1e-9, 1 - 1e-9],
                   [0.25, 0.75], [1, 0.5], [0.5, 1]]
        want = bilinear(albedo_texture(image, size), uv)
        np.testing.assert_array_equal(
            bilinear_of(albedo_texels(image, size), (size, size), uv), want)
        buf = oiio.ImageBuf(oiio.ImageSpec(w, h, 3, oiio.FLOAT))
        buf.set_pixels(oiio.ROI(), image)
        centres = (np.arange(size) + 0.5) / size
        looked_up = np.array([[buf.interppixel_NDC(float(u), float(v), "clamp")
                               for u in centres] for v in centres], np.float32)
        np.testing.assert_allclose(albedo_texture(image, size), np.clip(looked_up, 0, None),
                                   atol=1e-5)


def test_times_resampled_power_is_numpys_weight_of_the_resampled_image() -> None:
    """The albedo's weight after the blur made on the device from the albedo's own image
    (times_resampled_power) is numpy's max(resample_bilinear, 0) ** power times the
    texture, bit for bit for powers 1 and 1/2 (up, down, the same size, a 1 x 1 constant,
    values below 0 clipped), and within float32 rounding for another power (OpenCL's
    pow, checked against OpenImageIO's bilinear lookup, not this module's)."""
    import OpenImageIO as oiio

    rng = np.random.default_rng(7)
    for (h, w), size in (((37, 50), 64), ((64, 64), 64), ((90, 70), 40), ((1, 1), 16)):
        image = (rng.random((h, w, 3)) * 1.2 - 0.1).astype(np.float32)
        rgb = rng.random((size, size, 3)).astype(np.float32)
        albedo = np.clip(resample_bilinear(image, size), 0.0, None)
        for power, weight in ((0.5, np.sqrt(albedo)), (1.0, albedo)):
            got = rgb.copy()
            times_resampled_power(got, image, power)
            np.testing.assert_array_equal(got, rgb * weight)
    image = rng.random((20, 30, 3)).astype(np.float32)
    buf = oiio.ImageBuf(oiio.ImageSpec(30, 20, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(), image)
    centres = (np.arange(24) + 0.5) / 24
    looked_up = np.array([[buf.interppixel_NDC(float(u), float(v), "clamp") for u in centres]
                          for v in centres], np.float64)
    got = np.ones((24, 24, 3), np.float32)
    times_resampled_power(got, image, 0.3)
    np.testing.assert_allclose(got, looked_up ** 0.3, rtol=1e-5)
    with pytest.raises(ValueError, match="float32"):
        times_resampled_power(np.ones((4, 4, 3)), image, 0.5)
