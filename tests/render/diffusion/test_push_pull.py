"""Push-pull hole filling: the OpenCL version against the numpy reference, covered
texels untouched, odd and degenerate shapes, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.diffusion.push_pull import push_pull, push_pull_reference

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


@pytest.mark.parametrize(("shape", "channels"), [
    ((33, 47), 3), ((64, 64), 5), ((1, 9), 2), ((7, 1), 1), ((1, 1), 3), ((513, 300), 4),
])
def test_device_equals_the_numpy_reference(shape: tuple[int, int], channels: int) -> None:
    rng = np.random.default_rng(1)
    values = rng.random((*shape, channels)).astype(np.float32)
    cov = (rng.random(shape) > 0.7).astype(np.float32)
    out = push_pull(values, cov)
    ref = push_pull_reference(values, cov)
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(out[cov > 0], values[cov > 0])


@pytest.mark.parametrize(("shape", "channels"), [((33, 47), 3), ((64, 64), 1), ((1, 1), 3)])
def test_in_place_writes_the_same_maps_into_the_values(shape: tuple[int, int],
                                                       channels: int) -> None:
    """``in_place``: the result bit for bit as a new array's, in the values' own memory
    (float32, C-contiguous); other values (float64, strided) are left as they were and
    the result comes in a new array."""
    rng = np.random.default_rng(2)
    values = rng.random((*shape, channels)).astype(np.float32)
    cov = (rng.random(shape) > 0.7).astype(np.float32)
    want = push_pull(values, cov)
    mine = values.copy()
    got = push_pull(mine, cov, in_place=True)
    np.testing.assert_array_equal(got, want)
    assert np.shares_memory(got, mine) or shape == (1, 1)
    for other in (values.astype(np.float64), np.asfortranarray(values)):
        kept = other.copy()
        got = push_pull(other, cov, in_place=True)
        np.testing.assert_array_equal(got, want)
        assert not np.shares_memory(got, other)
        np.testing.assert_array_equal(other, kept)


def test_holes_take_their_surroundings_and_nothing_outside_their_range() -> None:
    # a hole inside a constant field takes the constant; holes between two fields take
    # values between them
    values = np.full((64, 64), 2.0, np.float32)
    cov = np.ones((64, 64), np.float32)
    cov[20:28, 21:30] = 0.0
    values[20:28, 21:30] = 99.0  # what the hole held must not show
    out = push_pull(values, cov)
    np.testing.assert_allclose(out, 2.0, rtol=1e-6)
    values = np.zeros((64, 64), np.float32)
    cov = np.zeros((64, 64), np.float32)
    values[:, :32], cov[:, :32] = 1.0, 1.0
    values[:, 48:], cov[:, 48:] = 3.0, 1.0
    out = push_pull(values, cov)
    assert np.all((out >= 1.0 - 1e-6) & (out <= 3.0 + 1e-6))


def test_nothing_covered_gives_zeros_and_fractional_coverage_keeps_values() -> None:
    values = np.full((16, 16, 3), 2.0, np.float32)
    assert not push_pull(values, np.zeros((16, 16), np.float32)).any()
    cov = np.full((16, 16), 0.25, np.float32)
    np.testing.assert_array_equal(push_pull(values, cov), values)


def test_mismatched_shapes_are_refused() -> None:
    with pytest.raises(InputError, match="push-pull"):
        push_pull(np.zeros((8, 8, 3)), np.zeros((8, 9)))


def test_dilation_copies_the_adjacent_chart_into_a_two_texel_ring() -> None:
    """Two charts two texels apart: each ring texel takes its own chart's edge value
    (axial neighbour first), texels beyond the ring keep the pyramid's fill."""
    from skinpipe.render.diffusion.push_pull import dilate_charts

    cov = np.zeros((12, 12), np.float32)
    cov[2:10, 2:5] = 1  # chart A, value 1
    cov[2:10, 7:10] = 1  # chart B, value 5, a two-texel gap from A
    values = np.where(cov > 0, np.where(np.arange(12) < 6, 1.0, 5.0)[None, :], 9.0)
    out = dilate_charts(values.astype(np.float32), cov)
    assert np.all(out[2:10, 5] == 1) and np.all(out[2:10, 6] == 5)  # the gap, split
    assert np.all(out[2:10, 0:2] == 1) and np.all(out[2:10, 10:12] == 5)
    assert out[0, 3] == 1 and out[11, 8] == 5  # two texels above and below
    np.testing.assert_array_equal(out[cov > 0], values[cov > 0])
    big = np.zeros((12, 12), np.float32)
    big[5, 5] = 1
    far = dilate_charts(np.where(big > 0, 2.0, 9.0).astype(np.float32), big)
    assert far[5, 8] == 9 and far[5, 7] == 2  # three texels away: untouched


@pytest.mark.parametrize("seed", range(4))
def test_dilation_ring_is_scipys_chessboard_distance(seed: int) -> None:
    """Against scipy's chessboard distance transform: the texels the dilation fills are
    exactly those 1-2 steps (8-connected) from a chart, and each copies a chart texel
    as many steps away as scipy says the nearest is (a step-by-step growth, pass after
    pass, cannot skip ahead or fall behind)."""
    from scipy.ndimage import distance_transform_cdt

    from skinpipe.render.diffusion.push_pull import GUTTER_RING, _nearest_sources

    rng = np.random.default_rng(seed)
    covered = rng.random((37, 53)) < 0.03 * (seed + 1)
    covered[5:9, 40:52] = True  # a chart touching the border
    dst, src = _nearest_sources.__wrapped__(covered.tobytes(), covered.shape, GUTTER_RING)
    steps = distance_transform_cdt(~covered, metric="chessboard")
    ring = (steps > 0) & (steps <= GUTTER_RING)
    np.testing.assert_array_equal(np.sort(dst), np.flatnonzero(ring))
    assert covered.ravel()[src].all()
    dy, dx = np.divmod(dst, covered.shape[1])
    sy, sx = np.divmod(src, covered.shape[1])
    np.testing.assert_array_equal(np.maximum(abs(dy - sy), abs(dx - sx)), steps.ravel()[dst])


def test_a_prepared_dilation_is_the_one_dilate_charts_reads() -> None:
    """prepare_dilation (the renderer runs it on a thread beside the filter) makes the
    gutter dilate_charts then reads for the same coverage, not another one; an all- or
    none-covered layout has none."""
    from skinpipe.render.diffusion.push_pull import (
        _nearest_sources,
        dilate_charts,
        prepare_dilation,
    )

    cov = np.zeros((16, 16), np.float32)
    cov[3:9, 4:12] = 1
    values = np.where(cov > 0, 2.0, 7.0).astype(np.float32)
    _nearest_sources.cache_clear()
    prepare_dilation(cov)
    assert _nearest_sources.cache_info().misses == 1
    out = dilate_charts(values.copy(), cov)
    assert _nearest_sources.cache_info().hits == 1
    assert out[2, 6] == 2 and out[0, 6] == 7
    prepare_dilation(np.ones((4, 4), np.float32))
    prepare_dilation(np.zeros((4, 4), np.float32))
    assert _nearest_sources.cache_info().misses == 1


def test_extrapolation_continues_each_chart_s_slope_into_its_ring() -> None:
    """A ramp of slope 1 a texel on a disc chart and another chart two texels from it:
    a bilinear lookup between a chart's edge texel and the texel beside it reads the
    ramp (a copy was off by the slope's half texel); each ring continues its own chart,
    the second ring keeps the copy, and nothing goes below zero."""
    from scipy.ndimage import binary_dilation

    from skinpipe.render.diffusion.push_pull import extrapolate_charts
    from skinpipe.render.shading import bilinear

    yy, xx = np.mgrid[0:40, 0:40]
    cov = (((yy - 20) ** 2 + (xx - 14) ** 2) < 10**2).astype(np.float32)
    cov[5:35, 27:30] = 1  # a second chart, two texels right of the disc
    ramp = np.where(xx < 26, 3.0 + xx, 100.0 - 30 * (xx - 26)).astype(np.float32)
    out = extrapolate_charts(np.where(cov > 0, ramp, 0.0).astype(np.float32), cov)
    disc = cov.copy()
    disc[:, 26:] = 0
    first = binary_dilation(disc > 0, np.ones((3, 3), bool)) & (disc == 0) & (xx < 26)
    np.testing.assert_allclose(out[first], ramp[first], atol=1e-4)
    assert out[20, 26] == 100.0  # the second chart's own slope, not the disc's
    assert out[20, 30] == 0.0 and out[20, 31] == 10.0  # 2 x 10 - 40 clamped; a copy
    uv = np.array([[(23.6 + 0.5) / 40, (20 + 0.5) / 40]])  # the disc's edge texel is 23
    np.testing.assert_allclose(bilinear(out, uv)[0], 3.0 + 23.6, atol=1e-4)
