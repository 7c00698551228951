"""Direct (one-pass FIR) Gaussian: radius rule, weights, against the exact Gaussian and
its float64 reference (interior and edge bands, odd sizes), borders, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.device.choice import open_device
from skinpipe.render.diffusion.blur_switch import prefers_direct
from skinpipe.render.diffusion.direct_blur import (
    FIR_MAX_ERROR,
    DirectBlur,
    band_columns,
    direct_kernels,
    direct_reference,
    direct_texel_reference,
    fir_parameter,
    fir_radius,
    fir_weight_table,
    fir_weights,
    truncation_error,
)

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


def test_radius_rule_reference_values() -> None:
    # the smallest radius within 6e-4 of the 2D peak (computed by hand from the sums)
    assert [fir_radius(s) for s in (0.5, 1.0, 2.0, 4.0)] == [2, 3, 7, 15]
    for s in (0.7, 1.0, 2.5, 4.0):
        r = fir_radius(s)
        assert truncation_error(s, r) <= FIR_MAX_ERROR < truncation_error(s, r - 1)


def test_weights_sum_to_one_and_keep_the_variance() -> None:
    # below a texel the parameter is solved for sigma^2 (a sampled Gaussian is narrower
    # than its parameter); elsewhere only the truncation takes variance off (< 0.5%)
    for s in (0.3, 0.5, 0.8, 1.0, 1.4, 2.0, 4.0):
        w = fir_weights(s)
        k = np.arange(-(w.size - 1), w.size)
        full = np.r_[w[:0:-1], w]
        assert full.sum() == pytest.approx(1.0, abs=1e-12)
        assert (k * k * full).sum() == pytest.approx(s * s, rel=5e-4 if s <= 0.8 else 5e-3)
    assert fir_parameter(0.5) == pytest.approx(0.525, abs=1e-3)
    assert fir_parameter(2.0) == 2.0
    assert np.all(np.diff(fir_weights(2.0)) < 0)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 3.0, 4.0])
def test_matches_the_exact_gaussian_to_1e3_of_the_peak(sigma: float) -> None:
    half = int(8 * sigma) + 8
    n = 2 * half + 1
    img = np.zeros((n, n, 4), np.float32)
    img[half, half] = 1.0
    got = DirectBlur(open_device(), n, n).blur(img, sigma, sigma)[..., 0]
    k = np.arange(-half, half + 1)
    g = np.exp(-k * k / (2 * sigma * sigma))
    g /= g.sum()
    exact = np.outer(g, g)
    assert np.abs(got - exact).max() / exact.max() < 1e-3
    assert got.sum() == pytest.approx(1.0, abs=1e-5)


@pytest.mark.parametrize(("h", "w", "su", "sv"), [
    (37, 53, 1.0, 2.0),      # narrower than one band: all edge path
    (300, 517, 3.0, 0.7),    # odd width: interior bands on 16-byte aligned rows
    (260, 1030, 4.2, 4.2),   # several strips and bands, partial last band
    (1, 1, 2.0, 2.0),
    (1024, 1030, 2.0, 1.0),  # 16 MiB and more: streaming stores
])
def test_opencl_agrees_with_the_float64_reference(h: int, w: int, su: float, sv: float) -> None:
    img = np.random.default_rng(3).random((h, w, 4)).astype(np.float32)
    ours = DirectBlur(open_device(), h, w).blur(img, su, sv)
    ref = direct_reference(img, su, sv)
    assert np.abs(ours - ref).max() / np.abs(ref).max() < 1e-5


def test_weight_table_rows_are_each_sigmas_kernel_at_the_widest_radius() -> None:
    sigmas = np.array([2.0, 0.4, 1.0, 1.7])
    table = fir_weight_table(sigmas)
    assert table.shape == (4, fir_radius(fir_parameter(2.0)) + 1)
    np.testing.assert_allclose(table[0], fir_weights(2.0), rtol=1e-12)
    np.testing.assert_allclose(table[:, 0] + 2 * table[:, 1:].sum(axis=1), 1.0, rtol=1e-12)
    k = np.arange(table.shape[1])
    variance = 2 * (k * k * table).sum(axis=1)
    # a longer cut than each sigma's own keeps more of its variance, never less
    np.testing.assert_allclose(variance, sigmas**2, rtol=5e-3)
    with pytest.raises(InputError, match="sigma"):
        fir_weight_table(np.array([1.0, 0.0]))


def _texel_case(h: int, w: int, seed: int) -> tuple[np.ndarray, ...]:
    """An image, u and v weight tables and random per-texel rows into them."""
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, 4)).astype(np.float32)
    tu = fir_weight_table(np.geomspace(0.4, 2.5, 9))
    tv = fir_weight_table(np.geomspace(0.3, 1.2, 5))
    iu = rng.integers(0, 9, (h, w)).astype(np.uint16)
    iv = rng.integers(0, 5, (h, w)).astype(np.uint16)
    return img, tu, tv, iu, iv


@pytest.mark.parametrize(("h", "w"), [(37, 53), (300, 517), (1, 1), (1024, 1030)])
def test_per_texel_weights_agree_with_the_float64_reference(h: int, w: int) -> None:
    # each texel's own row of weights: edge and interior (pair) bands, odd sizes, and a
    # 16 MiB texture (streaming stores)
    import pyopencl as cl

    img, tu, tv, iu, iv = _texel_case(h, w, 4)
    blur = DirectBlur(open_device(), h, w)
    blur.upload(img)
    flags = cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR
    bu, bv = (cl.Buffer(blur.ctx, flags, hostbuf=i) for i in (iu, iv))
    direct_kernels(open_device()).blur_per_texel(blur.buf_a, blur.buf_b, h, w, tu, tv, bu, bv)
    blur.queue.finish()
    blur.buf_a, blur.buf_b = blur.buf_b, blur.buf_a
    ours = blur.download()
    ref = direct_texel_reference(img, tu, tv, iu, iv)
    assert np.abs(ours - ref).max() / np.abs(ref).max() < 1e-5


def test_texels_outside_count_as_zero() -> None:
    # a constant image keeps its value inside and falls at the borders by the mass the
    # kernel puts outside: 1 - sum of the weights past the edge, per axis
    h, w, s = 64, 300, 2.0
    out = DirectBlur(open_device(), h, w).blur(np.ones((h, w, 4), np.float32), s, s)
    wts = fir_weights(s)
    edge = 1.0 - wts[1:].sum()  # at the first texel: half the kernel lies outside
    assert out[h // 2, w // 2, 0] == pytest.approx(1.0, abs=1e-6)
    assert out[h // 2, 0, 0] == pytest.approx(edge, abs=1e-6)
    assert out[0, 0, 0] == pytest.approx(edge * edge, abs=1e-6)


def test_band_fits_the_ring_budget_and_dispatch_rule() -> None:
    assert band_columns(3) == 128 and band_columns(8) == 64 and band_columns(40) == 16
    assert prefers_direct(open_device(), 1.0, 2.0) and prefers_direct(open_device(), 4.0, 0.5)
    assert not prefers_direct(open_device(), 1.0, 6.0)
    # per-texel weights cost more a tap: a narrower limit
    device = open_device()
    assert prefers_direct(device, 2.0, 2.0, per_texel=True)
    assert not prefers_direct(device, 4.0, 1.0, per_texel=True)


def test_bad_input_is_refused() -> None:
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(InputError, match="sigma"):
            fir_radius(bad)
    blur = DirectBlur(open_device(), 8, 8)
    with pytest.raises(InputError, match="texture"):
        blur.upload(np.zeros((8, 9, 4), np.float32))
    with pytest.raises(InputError, match="differ"):
        direct_kernels(open_device()).blur(blur.buf_a, blur.buf_a, 8, 8, 1.0, 1.0)
