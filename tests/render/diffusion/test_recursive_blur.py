"""Recursive (Deriche) Gaussian: against the exact Gaussian, its float64 reference,
its closed-form variance, and with extreme inputs."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.render.device.choice import open_device
from skinpipe.render.diffusion.recursive_blur import (
    QUANT_STEPS_PER_OCTAVE,
    QUANTIZE_CHUNK,
    RecursiveBlur,
    coefficient_table,
    deriche_coefficients,
    deriche_variance,
    quantized_log2,
    recursive_reference,
)

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


def _impulse_response(sigma: float) -> tuple[np.ndarray, np.ndarray]:
    half = int(8 * sigma) + 8
    img = np.zeros((2 * half + 1, 2 * half + 1, 4), np.float32)
    img[half, half] = 1.0
    got = RecursiveBlur(open_device(), 2 * half + 1, 2 * half + 1).blur(img, sigma, sigma)[..., 0]
    k = np.arange(-half, half + 1)
    g = np.exp(-k * k / (2 * sigma * sigma))
    g /= g.sum()
    return got, np.outer(g, g)


@pytest.mark.parametrize("sigma", [1.0, 2.0, 4.0, 16.0, 64.0])
def test_matches_the_exact_gaussian_to_1e3_of_the_peak(sigma: float) -> None:
    got, exact = _impulse_response(sigma)
    assert np.abs(got - exact).max() / exact.max() < 1e-3
    assert abs(got.sum() - 1.0) < 2e-4  # energy kept


def test_sub_texel_sigma_has_the_asked_variance() -> None:
    # below 0.8 texel the parameter is solved for sigma^2, as the gather kernel does
    got, _ = _impulse_response(0.5)
    k = np.arange(got.shape[0]) - got.shape[0] // 2
    var_u = float((got.sum(axis=0) * k * k).sum() / got.sum())
    assert var_u == pytest.approx(0.25, rel=2e-3)


def test_opencl_agrees_with_the_float64_reference_per_texel() -> None:
    rng = np.random.default_rng(4)
    h, w = 37, 53
    img = rng.random((h, w, 4)).astype(np.float32)
    su = rng.uniform(0.3, 9.0, (h, w))
    sv = rng.uniform(0.3, 9.0, (h, w))
    ours = RecursiveBlur(open_device(), h, w).blur(img, su, sv)
    ref = recursive_reference(img, su, sv)
    assert np.abs(ours - ref).max() / np.abs(ref).max() < 1e-5


def test_rows_longer_than_local_memory_blur_the_same_through_global_scratch(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """Where a device's local memory holds fewer texels than a row (a GPU's 48 KiB: 768
    texels), the pass keeps its rows in a global buffer: the same floats as in local
    memory, per texel and for one sigma, with a row count that is not a multiple of the
    rows a work item runs, and the float64 reference's values."""
    rng = np.random.default_rng(7)
    h, w = 39, 61
    img = rng.random((h, w, 4)).astype(np.float32)
    su = rng.uniform(0.3, 9.0, (h, w))
    sv = rng.uniform(0.3, 9.0, (h, w))
    blur = RecursiveBlur(open_device(), h, w)
    assert blur.iir.max_line >= max(h, w)  # every device the tests run on
    want = [blur.blur(img, *sigmas) for sigmas in ((su, sv), (3.5, 6.0))]
    monkeypatch.setattr(blur.iir, "max_line", 16)  # rows of 61 and 39 texels: past it
    monkeypatch.setattr(blur.iir, "_scratch", None)
    got = [blur.blur(img, *sigmas) for sigmas in ((su, sv), (3.5, 6.0))]
    for g, wnt in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, wnt)
    assert blur.iir._scratch.size >= 16 * 4 * w * 10  # ceil(39 / 4) items of 4 rows
    ref = recursive_reference(img, su, sv)
    assert np.abs(got[0] - ref).max() / np.abs(ref).max() < 1e-5


def test_closed_form_variance_matches_the_impulse_response() -> None:
    from scipy.signal import lfilter

    for sigma in (0.7, 3.0, 40.0):
        c = deriche_coefficients(sigma).reshape(2, 6)
        n = int(14 * sigma) + 60
        x = np.zeros(2 * n + 1)
        x[n] = 1.0
        y = np.zeros_like(x)
        for b0, b1, m1, m2, a1, a2 in c:
            y += lfilter([b0, b1], [1, a1, a2], x)
            y += lfilter([0, m1, m2], [1, a1, a2], x[::-1])[::-1]
        k = np.arange(-n, n + 1)
        assert y.sum() == pytest.approx(1.0, abs=1e-9)
        assert (k * k * y).sum() == pytest.approx(deriche_variance(sigma), rel=1e-6)


def test_table_is_finite_and_extreme_inputs_stay_finite() -> None:
    assert np.all(np.isfinite(coefficient_table()))
    img = np.zeros((16, 24, 4), np.float32)
    img[8, 12] = 1e30  # large but finite
    sig = np.full((16, 24), 1e6)  # clamped to the table's widest sigma
    out = RecursiveBlur(open_device(), 16, 24).blur(img, sig, np.zeros((16, 24)))
    assert np.all(np.isfinite(out))
    with pytest.raises(ValueError, match="texture must be"):
        RecursiveBlur(open_device(), 16, 24).blur(np.zeros((16, 16, 4)), 1.0, 1.0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_quantized_log2_in_chunks_is_the_whole_array_formula(dtype: type) -> None:
    # chunk borders, a short last chunk, a 2-D map and a scalar: round(1024 log2 x) as
    # one numpy expression over the whole array, bit for bit
    rng = np.random.default_rng(6)
    x = (0.05 * 2.0 ** rng.normal(0, 3, (3, QUANTIZE_CHUNK + 77))).astype(dtype)
    want = np.rint(QUANT_STEPS_PER_OCTAVE * np.log2(x)).astype(np.int32)
    got = quantized_log2(x)
    assert got.dtype == np.int32 and got.shape == x.shape
    np.testing.assert_array_equal(got, want)
    assert int(quantized_log2(dtype(2.0))) == QUANT_STEPS_PER_OCTAVE
