"""The wide terms summed on the surface (render.diffusion.surface_terms) against the
Gaussian's own closed forms: a lit half plane whose edge is a chart seam."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import erfc

from skinpipe.render.device.choice import Device
from skinpipe.render.diffusion.surface_terms import (
    MAX_SPACING_MM,
    SURFACE_SIGMA_MM,
    SurfacePoints,
    block_level,
    surface_light,
    surface_points,
)

TEXEL_MM = 0.1
HALF = 64  # texels a chart is wide; each chart is HALF x HALF


def _mirrored_plane(keep_texels: bool = False, finest: int = 0) -> SurfacePoints:
    """A 12.8 x 6.4 mm plane at z = 0 in two charts side by side in the texture: chart 0
    (texels x < 64) is the half x < 0, chart 1 the half x > 0 mirrored along u, so the
    two meet in 3D at x = 0 between texel 63 and texel 127, far apart in the texture."""
    h, w = HALF, 2 * HALF
    chart = np.zeros((h, w), np.int32)
    chart[:, HALF:] = 1
    triangle = chart.copy()
    jac = np.zeros((2, 3, 2))
    jac[0, 0, 0], jac[1, 0, 0] = TEXEL_MM, -TEXEL_MM
    jac[:, 1, 1] = TEXEL_MM

    def at(texel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x, y = texel % w, texel // w
        u = np.where(x < HALF, x - HALF + 0.5, (w - 1 - x) + 0.5)
        pos = np.stack([u * TEXEL_MM, (y + 0.5 - h / 2) * TEXEL_MM, np.zeros(x.size)], axis=1)
        normal = np.zeros_like(pos)
        normal[:, 2] = 1.0
        return pos.astype(np.float32), normal.astype(np.float32)

    return surface_points(chart, None, triangle, jac, at, 1.0, TEXEL_MM, finest,
                          keep_texels=keep_texels)


def test_a_term_goes_on_the_surface_where_it_is_wide_and_its_blocks_a_texel_or_more() -> None:
    assert block_level(0.9 * SURFACE_SIGMA_MM**2, 0.01) is None
    assert block_level(1.0, 1.5) is None  # blocks narrower than a texel
    assert block_level(1.0, 0.1) == 3  # sigma / 1.0 = 1 mm: blocks of 8 texels
    # the widest blocks stay within MAX_SPACING_MM however wide the term
    level = block_level(100.0, 0.025)
    assert level is not None and 0.025 * 2**level <= MAX_SPACING_MM < 0.025 * 2 ** (level + 1)


def test_blocks_hold_their_texels_area_and_the_mean_of_a_linear_light_at_their_centroid(
) -> None:
    points = _mirrored_plane()
    blocks = points.level(3)
    assert blocks.point[:, 3].sum() == pytest.approx(12.8 * 6.4, rel=1e-6)
    # no block takes texels of both charts: the seam at x = 0 is between blocks
    assert np.all(blocks.point[:, 0] != 0.0)
    light = np.zeros((HALF, 2 * HALF, 3), np.float32)
    pos, _ = _texel_positions(points)
    light.reshape(-1, 3)[points.texel] = np.stack(
        [1.0 + 0.3 * pos[:, 0], 2.0 - 0.1 * pos[:, 1], np.ones(pos.shape[0])], axis=1)
    mean = points.means(3, light)
    want = np.stack([1.0 + 0.3 * blocks.point[:, 0], 2.0 - 0.1 * blocks.point[:, 1],
                     np.ones(blocks.point.shape[0])], axis=1)
    np.testing.assert_allclose(mean, want, rtol=0, atol=1e-5)


def _texel_positions(points: SurfacePoints) -> tuple[np.ndarray, np.ndarray]:
    kept = _mirrored_plane(keep_texels=True, finest=points.finest).texel_surface
    assert kept is not None
    return kept[:, 0, :3], kept[:, 1, :3]


def test_light_crosses_a_seam_as_the_gaussian_says(cl_device: Device) -> None:
    """The half x < -0.3 mm of the plane lit: its light spreads into chart 1 across their
    seam as the closed form of a Gaussian of variance v, E(x) = erfc((x + 0.3) /
    sqrt(2 v)) / 2, read at points along a line across it and at the texels (a texture
    output). The blocks, the sum over points and the read back add up to v: without the
    read's width taken off step 1, 3.7% of the lit level off. An edge on a block's border
    is the worst case (the blocks then blur it none): 1.4% off."""
    variance, edge = 1.0, -0.3
    points = _mirrored_plane(keep_texels=True)
    assert points.texel_surface is not None
    light = np.zeros((HALF, 2 * HALF, 3), np.float32)
    light.reshape(-1, 3)[points.texel[points.texel_surface[:, 0, 0] < edge]] = 1.0
    level = block_level(variance, TEXEL_MM)
    assert level == 3
    weights = np.ones((1, 1, 3), np.float32)
    got = surface_light(cl_device, points, light, np.array([variance]), [level], weights)
    x = np.linspace(-3.0, 3.0, 121)
    at = np.stack([x, np.full_like(x, 0.13), np.zeros_like(x)], axis=1)
    up = np.tile([0.0, 0.0, 1.0], (x.size, 1))
    read = got.at(cl_device, at, up)

    def want(x_mm: np.ndarray | float) -> np.ndarray:
        return 0.5 * erfc((np.asarray(x_mm) - edge) / math.sqrt(2 * variance))

    error = np.abs(read - want(x)[:, None]).max()
    assert error < 0.007, error
    # the texels of both charts beside the seam, and at the plane's ends
    texels = got.at_texels(cl_device, points, light.shape)
    row = texels[HALF // 2, :, 0]
    for texel, x_mm in ((HALF - 1, -0.05), (2 * HALF - 1, 0.05), (0, -6.35), (HALF, 6.35)):
        assert row[texel] == pytest.approx(want(x_mm), abs=0.007)
    # the flux (mm^2 x light, three channels) is the lit part's
    assert got.flux == pytest.approx(3 * 6.1 * 6.4, rel=0.01)


def test_the_far_side_of_a_thin_part_takes_no_light_along_the_surface(cl_device: Device
                                                                     ) -> None:
    """Two sheets 0.5 mm apart facing away from each other (the two sides of an ear): the
    lit one's light does not reach the other by the surface sum (it goes through the
    volume, light.thin_parts)."""
    points = _mirrored_plane()
    light = np.zeros((HALF, 2 * HALF, 3), np.float32)
    light[:] = 1.0
    got = surface_light(cl_device, points, light, np.array([1.0]), [3],
                        np.ones((1, 1, 3), np.float32))
    below = np.array([[0.0, 0.0, -0.5]])
    assert got.at(cl_device, below, np.array([[0.0, 0.0, -1.0]]))[0, 0] == 0.0
    assert got.at(cl_device, below, np.array([[0.0, 0.0, 1.0]]))[0, 0] == pytest.approx(
        1.0, abs=1e-3)
