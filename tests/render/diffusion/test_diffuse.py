"""Diffusion: the gather blur vs its float64 reference; the recursive pyramid diffusion
against exact normalised convolutions; the profile reproduced in mm; bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.profile.models import fit_error_eq2c, sum_of_gaussians
from skinpipe.profile.reference_data import DEON_2007_SKIN
from skinpipe.render.device.choice import open_device
from skinpipe.render.diffusion.diffuse import diffuse
from skinpipe.render.diffusion.gather import OpenCLBlur, blur_reference, diffuse_gather
from skinpipe.render.diffusion.inputs import unit_region_weights
from skinpipe.render.diffusion.layout import _added_variance_texels2, ranked_step

# every test here runs on each OpenCL device that passes the probe (conftest)
pytestmark = pytest.mark.usefixtures("cl_device")


def test_opencl_matches_float64_reference() -> None:
    rng = np.random.default_rng(0)
    h, w = 40, 56
    image = rng.random((h, w, 4)).astype(np.float32)
    sigma_u = rng.uniform(0.1, 6.0, (h, w))
    sigma_v = rng.uniform(0.1, 6.0, (h, w))
    coverage = (rng.random((h, w)) > 0.15).astype(np.float32)
    ours = OpenCLBlur(open_device(), coverage).blur(image, sigma_u, sigma_v)
    ref = blur_reference(image, sigma_u, sigma_v, coverage)
    np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-6)


def test_constant_field_stays_constant_at_chart_borders() -> None:
    h, w = 32, 32
    coverage = np.zeros((h, w), np.float32)
    coverage[4:28, 6:20] = 1.0
    image = np.ones((h, w, 4), np.float32)
    out = OpenCLBlur(open_device(), coverage).blur(image, np.full((h, w), 5.0),
                                                   np.full((h, w), 5.0))
    np.testing.assert_allclose(out[coverage > 0], 1.0, rtol=1e-5)


def _pencil(n: int, mm_u: float, mm_v: float, variances: np.ndarray, weights: np.ndarray):
    """Diffuse one lit texel on a flat patch; return radii (mm) and the profile per mm^2."""
    e = np.zeros((n, n, 3), np.float32)
    c = n // 2
    e[c, c] = 1.0
    cov = np.ones((n, n), np.float32)
    out, stats = diffuse(e, np.full((n, n), mm_u), np.full((n, n), mm_v), cov, variances,
                         weights)
    yy, xx = np.mgrid[0:n, 0:n]
    r = np.hypot((xx - c) * mm_u, (yy - c) * mm_v).ravel()
    return r, out.reshape(-1, 3) / (mm_u * mm_v), stats


@pytest.mark.parametrize(("mm_u", "mm_v"), [(0.05, 0.05), (0.1, 0.1), (0.05, 0.09)])
def test_pencil_light_reproduces_the_profile_in_mm(mm_u: float, mm_v: float) -> None:
    # d'Eon's profile on a patch wide enough (+-11 mm) for its widest term (sigma 2.7 mm)
    v, w = DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights
    n = int(2 * 11.0 / min(mm_u, mm_v)) | 1
    r, got, _ = _pencil(n, mm_u, mm_v, v, w)
    sel = (r > 0.3) & (r < 3.5)
    order = np.argsort(r[sel])
    rr, gg = r[sel][order], got[sel][order]
    truth = sum_of_gaussians(v, w, rr)
    assert fit_error_eq2c(rr, gg, truth).max() < 0.02


def test_pencil_under_a_one_texture_term_cap_reproduces_the_profile(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # the term buffer's byte cap (large textures) splits the terms into batches; the
    # pencil still gives d'Eon's profile (the analytic sum of Gaussians) and its energy
    import skinpipe.render.diffusion.diffuse as diffuse_module

    v, w = DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights
    mm = 0.1
    n = int(2 * 11.0 / mm) | 1
    monkeypatch.setattr(diffuse_module, "TERM_BUFFER_MAX_BYTES", 1)  # each term its own batch
    r, got, _ = _pencil(n, mm, mm, v, w)
    sel = (r > 0.3) & (r < 3.5)
    order = np.argsort(r[sel])
    rr, gg = r[sel][order], got[sel][order]
    assert fit_error_eq2c(rr, gg, sum_of_gaussians(v, w, rr)).max() < 0.02
    np.testing.assert_allclose(got.sum(axis=0) * mm * mm, 1.0, rtol=2e-3)


def test_energy_is_conserved_away_from_borders() -> None:
    import skinpipe.render.diffusion.layout as layout_module

    v = np.array([0.05, 0.5])
    w = np.array([[0.4, 0.5, 0.6], [0.6, 0.5, 0.4]])
    _, got, stats = _pencil(401, 0.05, 0.05, v, w)
    total = got.sum(axis=0) * 0.05 * 0.05
    np.testing.assert_allclose(total, 1.0, rtol=2e-4)
    # each term on the coarsest level where it is still LEVEL_MIN_SIGMA_TEXELS wide: the
    # wide one (sigma 14 texels) on a coarser level than the narrow one (4.5 texels)
    expect = [int(math.log2(sg / layout_module.LEVEL_MIN_SIGMA_TEXELS)) for sg in (4.47, 14.1)]
    assert stats.levels == expect and expect[1] > expect[0]


def test_zero_weight_terms_are_skipped() -> None:
    v = np.array([0.0004, 0.2, 1.0])
    w = np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    _, _, stats = _pencil(41, 0.1, 0.1, v, w)
    assert any("zero weight" in s for s in stats.skipped)
    assert any("narrower than a quarter texel" in s for s in stats.skipped)


def _normalised_convolution(e: np.ndarray, cov: np.ndarray, sigma_texels: float) -> np.ndarray:
    """Exact float64 sum G * (E cov) / G * cov (untruncated Gaussian, zero outside)."""
    from scipy.ndimage import gaussian_filter

    def g(x: np.ndarray) -> np.ndarray:
        return gaussian_filter(x, sigma_texels, mode="constant", truncate=12.0)

    a = g(cov.astype(np.float64))
    with np.errstate(invalid="ignore", divide="ignore"):  # 0/0 far off the chart: NaN
        return np.stack([g(e[..., c] * cov) for c in range(3)], axis=-1) / a[..., None]


@pytest.mark.parametrize("sigma_texels", [0.8, 3.0, 12.0, 40.0])
def test_one_term_matches_the_exact_normalised_convolution(sigma_texels: float) -> None:
    # smooth irradiance on a disc-shaped chart with a hole: pyramid levels 0-3
    n = 160
    rng = np.random.default_rng(1)
    yy, xx = np.mgrid[0:n, 0:n]
    cov = ((np.hypot(xx - 80, yy - 75) < 70) & (np.hypot(xx - 100, yy - 90) > 12)).astype(
        np.float32)
    from scipy.ndimage import gaussian_filter
    e = np.stack([gaussian_filter(rng.random((n, n)), 3.0) for _ in range(3)], -1)
    e = e.astype(np.float32)
    mm = 0.1
    v = np.array([(sigma_texels * mm) ** 2])
    got, stats = diffuse(e, np.full((n, n), mm), np.full((n, n), mm), cov, v, np.ones((1, 3)))
    ref = _normalised_convolution(e, cov, sigma_texels)
    sel = cov > 0
    err = np.abs(got[sel] - ref[sel]).max() / np.abs(ref[sel]).max()
    assert err < 5e-3, (stats.levels, err)
    assert not np.any(got[~sel])  # texels off the chart take nothing
    # narrow blurs (at their level) run the one-pass direct blur, wide ones the
    # recursive one (two passes)
    assert stats.passes == (1 if sigma_texels / 2 ** stats.levels[0] < 4 else 2)


@pytest.mark.parametrize("level", [1, 2, 3])
def test_a_term_on_a_pyramid_level_keeps_its_centre_and_variance(
        level: int, monkeypatch: pytest.MonkeyPatch) -> None:
    # the pyramid's own spread is taken off the blur: through level k an impulse
    # comes back centred where it was, with variance v (averaged over its 2^k phases)
    import skinpipe.render.diffusion.layout as layout_module

    assert _added_variance_texels2(0) == 0.0
    n = 96
    sigma = 0.6 * 2**level  # 0.6 of a level texel: the table matches variance there
    v = sigma**2 + _added_variance_texels2(level)
    monkeypatch.setattr(layout_module, "LEVEL_MIN_SIGMA_TEXELS", 0.999 * math.sqrt(v) / 2**level)
    spread = []
    for phase in range(2**level):
        e = np.zeros((n, n, 3), np.float32)
        c = 40 + phase
        e[c, c] = 1.0
        got, stats = diffuse(e, np.ones((n, n)), np.ones((n, n)), np.ones((n, n), np.float32),
                             np.array([v]), np.ones((1, 3)))
        assert stats.levels == [level]
        row = got[..., 0].sum(axis=0)
        x = np.arange(n)
        mean = (row * x).sum() / row.sum()
        # (float32 rounding: 1.5e-3 at level 3, a term of 0.6 level texels)
        assert mean == pytest.approx(c, abs=2e-3)
        spread.append(((x - mean) ** 2 * row).sum() / row.sum())
    assert np.mean(spread) == pytest.approx(v, rel=0.01)


def test_pencil_on_a_stretched_patch_follows_the_local_texel_size() -> None:
    # mm per texel grows 0.04 -> 0.08 across u: the profile in mm holds at both ends
    v, w = DEON_2007_SKIN.variances_mm2[:4], DEON_2007_SKIN.weights[:4]
    w = w / w.sum(axis=0)
    n = 301
    mm_u = np.tile(np.linspace(0.04, 0.08, n), (n, 1))
    mm_v = np.full((n, n), 0.05)
    for cx in (90, 210):
        e = np.zeros((n, n, 3), np.float32)
        e[150, cx] = 1.0
        out, _ = diffuse(e, mm_u, mm_v, np.ones((n, n), np.float32), v, w)
        # distances in mm along u: integrate the local texel size
        x_mm = np.concatenate([[0.0], np.cumsum(0.5 * (mm_u[0, 1:] + mm_u[0, :-1]))])
        r = np.abs(x_mm - x_mm[cx])
        sel = np.flatnonzero((r > 0.15) & (r < 1.0))
        sel = sel[np.argsort(r[sel])]
        got = out[150, sel] / (mm_u[150, sel, None] * 0.05)
        # the line through the light: sum_i w_i G_2D(v_i) at (x, 0)
        truth = sum_of_gaussians(v, w, r[sel])
        assert fit_error_eq2c(r[sel], got, truth).max() < 0.03


def test_recursive_and_gather_diffusion_agree_on_a_smooth_field() -> None:
    rng = np.random.default_rng(3)
    n = 96
    from scipy.ndimage import gaussian_filter
    e = np.stack([gaussian_filter(rng.random((n, n)), 4.0) for _ in range(3)], -1)
    mm = np.full((n, n), 0.1)
    v, w = DEON_2007_SKIN.variances_mm2[:5], DEON_2007_SKIN.weights[:5]
    cov = np.ones((n, n), np.float32)
    ours, _ = diffuse(e, mm, mm, cov, v, w)
    gather, _ = diffuse_gather(e, mm, mm, cov, v, w)
    inner = slice(20, -20)
    assert np.abs(ours[inner, inner] - gather[inner, inner]).max() < 2e-3 * gather.max()


@pytest.mark.parametrize(("case", "message"), [
    ("nan_irradiance", "irradiance"),
    ("zero_mm", "mm per texel"),
    ("descending", "ascending"),
    ("weights_shape", "term weights"),
])
def test_bad_input_is_refused_with_the_offending_value(case: str, message: str) -> None:
    n = 16
    e = np.ones((n, n, 3), np.float32)
    mm = np.full((n, n), 0.1)
    cov = np.ones((n, n), np.float32)
    v = np.array([0.01, 0.1])
    w = np.full((2, 3), 0.5)
    if case == "nan_irradiance":
        e[3, 5, 1] = np.nan
    elif case == "zero_mm":
        mm = mm.copy()
        mm[2, 7] = 0.0
    elif case == "descending":
        v = v[::-1].copy()
    else:
        w = np.full((3, 3), 0.5)
    with pytest.raises(InputError, match=message):
        diffuse(e, mm, mm, cov, v, w)


def test_extreme_variances_keep_energy() -> None:
    # a term far narrower than a texel and one as wide as the texture
    v = np.array([1e-8, 1e4])
    w = np.array([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]])
    _, got, _ = _pencil(65, 0.1, 0.1, v, w)
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got.sum(axis=0) * 0.01, 1.0, rtol=1e-3)


def test_a_prepared_layout_serves_many_diffusions_like_a_fresh_one() -> None:
    # the layout keeps its device maps and work buffers between calls: different term
    # sets (other levels, merged equal variances, a sub-texel term) and irradiances
    # on it give what a fresh `diffuse` gives, and a wrong-sized irradiance is refused
    from skinpipe.render.diffusion.diffuse import diffuse_prepared
    from skinpipe.render.diffusion.layout import DiffusionLayout

    rng = np.random.default_rng(5)
    n = 75  # odd: pyramid levels of odd size, rows not a multiple of four
    yy, xx = np.mgrid[0:n, 0:n]
    cov = (np.hypot(xx - 37, yy - 40) < 33).astype(np.float32)
    mm_u = np.tile(np.linspace(0.05, 0.09, n), (n, 1))
    mm_v = np.full((n, n), 0.07)
    rw = np.stack([xx / (n - 1), 1 - xx / (n - 1)], -1)
    layout = DiffusionLayout(open_device(), mm_u, mm_v, cov, rw)
    cases = [(np.array([1e-6, 0.004, 0.004, 0.3]), rng.random((2, 4, 3))),
             (np.array([0.01, 0.5, 2.0]), rng.random((2, 3, 3))),
             (np.array([1e-6, 0.004, 0.004, 0.3]), rng.random((2, 4, 3)))]
    for v, w in cases:
        e = rng.random((n, n, 3)).astype(np.float32)
        got, stats = diffuse_prepared(layout, e, v, w)
        fresh, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
        np.testing.assert_array_equal(got, fresh)
        assert got.shape == (n, n, 3) and got.flags.c_contiguous
    assert any("pass shared" in s for s in stats.skipped)
    with pytest.raises(InputError, match="like its layout"):
        diffuse_prepared(layout, np.ones((n, n + 1, 3), np.float32), v, w)


def test_a_layout_lets_its_work_go_and_makes_it_again_the_same() -> None:
    # a render's last diffusion lets the work buffers and level tiles go before the
    # push-pull (0.6 GB at texture 4096); a later diffusion on the layout (tiles made
    # again from its surface) gives the same floats
    from skinpipe.render.diffusion.diffuse import diffuse_prepared
    from skinpipe.render.diffusion.layout import DiffusionLayout

    e, mm_u, mm_v, cov, rw = _stretched_layout(90)
    v, w = np.array([0.002, 0.05, 0.6, 3.0]), np.random.default_rng(2).random((2, 4, 3))
    layout = DiffusionLayout(open_device(), mm_u, mm_v, cov, rw)
    before, _ = diffuse_prepared(layout, e, v, w)
    assert layout._buffers and layout._grids
    layout.release_work()
    assert not layout._buffers and not layout._grids
    after, _ = diffuse_prepared(layout, e, v, w)
    np.testing.assert_array_equal(after, before)


def _stretched_layout(n: int) -> tuple[np.ndarray, ...]:
    """Irradiance, mm per texel growing 0.05 -> 0.09 mm along u and 0.06 -> 0.08 along v,
    a disc of coverage and two regions blending across u."""
    rng = np.random.default_rng(8)
    yy, xx = np.mgrid[0:n, 0:n]
    cov = (np.hypot(xx - n / 2, yy - n / 2) < 0.45 * n).astype(np.float32)
    mm_u = np.tile(np.linspace(0.05, 0.09, n), (n, 1))
    mm_v = np.tile(np.linspace(0.06, 0.08, n)[:, None], (1, n))
    rw = np.stack([xx / (n - 1), 1 - xx / (n - 1)], -1).astype(np.float32)
    return rng.random((n, n, 3)).astype(np.float32), mm_u, mm_v, cov, rw


def test_narrow_terms_on_a_stretched_layout_are_each_texels_own_gaussian() -> None:
    # per-texel direct blur (one pass a term): each texel's Gaussian of v / (mm per
    # texel)^2 on its own axis, as a normalised convolution, against float64
    from skinpipe.render.diffusion.direct_blur import direct_texel_reference, fir_weight_table
    from skinpipe.render.diffusion.recursive_blur import QUANT_STEPS_PER_OCTAVE, quantized_log2

    n = 131
    e, mm_u, mm_v, cov, rw = _stretched_layout(n)
    v = np.array([0.004, 0.02])
    w = np.array([[[0.3, 0.5, 0.6], [0.7, 0.5, 0.4]], [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]])
    got, stats = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    assert stats.passes == 2 and stats.levels == [0, 0]
    expect = np.zeros((n, n, 3))
    rgba = np.concatenate([e * cov[..., None], cov[..., None]], -1)
    from scipy.ndimage import distance_transform_edt

    _, (ny, nx) = distance_transform_edt(cov == 0, return_indices=True)
    # the weights as the layout reads them: half floats, summing to 1
    held = unit_region_weights(rw.astype(np.float16).astype(np.float32))
    for i, var in enumerate(v):
        tables, rows = [], []
        for m in (mm_u, mm_v):
            # the kernel's sizes: off the charts the nearest chart texel's (a tile's
            # margin extrapolates its chart), on the log2 grid, from the 1e-4 quantile up
            m = np.where(cov > 0, m, m[ny, nx]).astype(np.float32)
            q = quantized_log2(m)
            lo = int(np.floor(np.quantile(q, 1e-4)))
            sigma = math.sqrt(var) / 2.0 ** (np.arange(lo, q.max() + 1) / QUANT_STEPS_PER_OCTAVE)
            tables.append(fir_weight_table(sigma))
            rows.append(np.maximum(q - lo, 0))
        t = direct_texel_reference(rgba, tables[0], tables[1], rows[0], rows[1])
        expect += (held @ w[:, i]) * t[..., :3] / np.maximum(t[..., 3:], 1e-30)
    inside = cov > 0
    assert np.abs(got - expect)[inside].max() < 1e-5 * np.abs(expect).max()
    assert np.all(got[~inside] == 0)


def test_a_few_tiny_texels_do_not_set_the_direct_radius() -> None:
    # three degenerate texels ten times smaller than the rest: they are blurred as the
    # 1e-4 quantile's size and counted, the blur stays one direct pass
    n = 200
    e, mm_u, mm_v, cov, rw = _stretched_layout(n)
    mm_u[100, 50:53] = 0.005
    v, w = np.array([0.02]), np.full((2, 1, 3), 1.0)
    got, stats = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    assert stats.passes == 1
    assert any("3 texel sizes below" in s for s in stats.skipped)
    assert np.all(np.isfinite(got))


def test_term_batches_add_up_like_one(monkeypatch: pytest.MonkeyPatch) -> None:
    # blurred terms are kept TERM_BUFFER_TEXTURES at a time before they are added up;
    # one at a time (an accumulator pass between batches) gives the same sum
    import skinpipe.render.diffusion.diffuse as diffuse_module

    n = 96
    e, mm_u, mm_v, cov, rw = _stretched_layout(n)
    v, w = DEON_2007_SKIN.variances_mm2, np.stack([DEON_2007_SKIN.weights] * 2)
    one, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    monkeypatch.setattr(diffuse_module, "TERM_BUFFER_TEXTURES", 1)
    assert len(diffuse_module._term_batches([n * n * 16] * 3 + [0], n * n * 16)) == 3
    batched, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    np.testing.assert_allclose(batched, one, rtol=1e-6, atol=1e-7)


def test_term_buffer_byte_cap_batches_and_adds_up_like_one(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # the blurred terms' buffer is capped in bytes too (large textures): under a cap of
    # one texture the terms go in several batches, and the sum is the same
    import skinpipe.render.diffusion.diffuse as diffuse_module

    n = 96
    e, mm_u, mm_v, cov, rw = _stretched_layout(n)
    v, w = DEON_2007_SKIN.variances_mm2, np.stack([DEON_2007_SKIN.weights] * 2)
    one, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    seen: list[int] = []
    batches = diffuse_module._term_batches

    def spy(sizes: list[int], budget: int) -> list[dict[int, tuple[int, int]]]:
        out = batches(sizes, budget)
        seen.append(len(out))
        return out

    monkeypatch.setattr(diffuse_module, "_term_batches", spy)
    monkeypatch.setattr(diffuse_module, "TERM_BUFFER_MAX_BYTES", n * n * 16)
    capped, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    assert seen and max(seen) > 1
    np.testing.assert_allclose(capped, one, rtol=1e-6, atol=1e-7)


@pytest.mark.parametrize("texels", [1, 63, 64, 65, 1000])
def test_region_presence_is_each_regions_maximum_above_zero(texels: int) -> None:
    """The regions any texel uses, grouped 64 texels a row for speed: numpy's own
    maximum over every texel says the same, whatever the count's remainder."""
    from skinpipe.render.diffusion.inputs import _region_presence

    rng = np.random.default_rng(texels)
    weights = (rng.random((texels, 1, 5)) * (rng.random((texels, 1, 5)) < 0.02)
               ).astype(np.float32)
    weights[-1, 0, 4] = 0.5  # a region only the last texel uses
    weights[:, :, 1] = 0.0
    np.testing.assert_array_equal(_region_presence(weights),
                                  weights.reshape(-1, 5).max(axis=0) > 0)


@pytest.mark.parametrize("n", [1, 9, 10007])
@pytest.mark.parametrize("spread", [0, 40, 30000])
def test_ranked_step_is_numpys_partition_and_count(n: int, spread: int) -> None:
    # the direct blur's lowest step: the rank-th smallest texel step and how many lie
    # below it, against np.partition and a count (one step, a few octaves, a wide span)
    q = np.random.default_rng(n + spread).normal(-7000, spread + 1e-9, n).astype(np.int32)
    for rank in sorted({0, min(8, n - 1), n // 2, n - 1}):
        lo = int(np.partition(q, rank)[rank])
        assert ranked_step(q, rank) == (lo, int((q < lo).sum()))


@pytest.mark.parametrize("path", ["prepared", "gather"])
def test_region_weights_are_read_as_a_partition_of_unity(path: str) -> None:
    # weights that sum to 0.5 or 2 at every texel blur as the ones that sum to 1
    e, mm_u, mm_v, cov, rw = _stretched_layout(40)
    v = np.array([0.004, 0.02])
    w = np.array([[[0.3, 0.5, 0.6], [0.7, 0.5, 0.4]], [[0.5, 0.5, 0.5], [0.5, 0.5, 0.5]]])
    blur = diffuse if path == "prepared" else diffuse_gather
    ones, _ = blur(e, mm_u, mm_v, cov, v, w, rw)
    for scale in (0.5, 2.0):
        scaled, _ = blur(e, mm_u, mm_v, cov, v, w, rw * np.float32(scale))
        np.testing.assert_allclose(scaled, ones, rtol=1e-6, atol=1e-7)



def test_region_presence_reads_half_weights_by_their_bits() -> None:
    from skinpipe.render.diffusion.inputs import _region_presence

    rw = np.zeros((130, 70, 4), np.float16)  # rows past a whole number of 64-texel groups
    rw[..., 0] = 1.0
    rw[129, 69, 2] = np.float16(6e-8)  # one texel, a subnormal half
    np.testing.assert_array_equal(_region_presence(rw), [True, False, True, False])
    np.testing.assert_array_equal(_region_presence(rw.astype(np.float32)),
                                  [True, False, True, False])


def test_terms_alone_in_their_batch_skip_the_term_buffer_bit_for_bit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # a term alone in its batch goes to the work buffer `tmp` (one direct pass) or over
    # its level's `source` (the level's last term, recursive) instead of the term
    # buffer, and the other terms to tmp's room past their levels' atlases; the sum is
    # the same bit for bit as through a term buffer of its own
    import skinpipe.render.diffusion.diffuse as diffuse_module
    import skinpipe.render.diffusion.layout as layout_module

    n = 256  # coarse terms beside level 1 in tmp's room (not at 160: margins)
    e, mm_u, mm_v, cov, rw = _stretched_layout(n)
    v, w = DEON_2007_SKIN.variances_mm2, np.stack([DEON_2007_SKIN.weights] * 2)
    monkeypatch.setattr(diffuse_module, "TERM_BUFFER_MAX_BYTES", 1)  # each term its own batch
    plan = diffuse_module._alone_into
    chosen: list[dict[int, str]] = []

    def spy(*args: object) -> dict[int, str]:
        chosen.append(plan(*args))  # type: ignore[arg-type]
        return chosen[-1]

    asked: list[str] = []
    own_buffer = layout_module.DiffusionLayout.buffer

    def buffer(self: layout_module.DiffusionLayout, name: str, nbytes: int) -> object:
        asked.append(name)
        return own_buffer(self, name, nbytes)

    monkeypatch.setattr(diffuse_module, "_alone_into", spy)
    monkeypatch.setattr(layout_module.DiffusionLayout, "buffer", buffer)
    alone, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    assert {"tmp", "source"} <= set(chosen[0].values())
    # the other terms (coarser levels') in tmp's room past their levels' atlases
    assert "terms" not in asked and len(chosen[0]) < len(v)
    monkeypatch.setattr(diffuse_module, "_alone_into", lambda *args: {})
    asked.clear()
    through_terms, _ = diffuse(e, mm_u, mm_v, cov, v, w, rw)
    assert "terms" in asked
    np.testing.assert_array_equal(alone, through_terms)


def test_region_weights_made_from_the_triangles_diffuse_as_the_map() -> None:
    """A layout given the rasterizer's arrays (TexelRegions) makes each texel's region
    weights where the accumulation reads them, in float32: the diffusion of one reading
    the maps' half floats within their rounding (three regions, blends of two and of
    three; measured 1.2e-4 relative at most on PoCL and Intel's runtime), without
    holding the map."""
    from skinpipe.render.diffusion.diffuse import diffuse_prepared
    from skinpipe.render.diffusion.layout import DiffusionLayout
    from skinpipe.render.diffusion.terms import diffusion_terms
    from skinpipe.render.surface.texture_maps import rasterize

    from ...render_scenes import exact_fit, grid_patch

    fits = [exact_fit(name, DEON_2007_SKIN.variances_mm2[:4] * s, DEON_2007_SKIN.weights[:4])
            for name, s in (("a", 1.0), ("b", 3.0), ("c", 0.5))]
    pts, tris, uv = grid_patch(24, 40.0)
    # three ramps that overlap: some texels blend two regions, some all three
    t = np.clip((pts[:, :2] + 4.0) / 8.0, 0.0, 1.0)
    weights = np.stack([(1 - t[:, 0]) * (1 - t[:, 1]), t[:, 0], (1 - t[:, 0]) * t[:, 1]], 1)
    maps = rasterize(pts, tris, uv * 0.9 + 0.05, tris, 192, 0.001, weights)
    assert maps.texel_regions is not None and maps.region_weights is not None
    blends = (maps.region_weights > 0).sum(axis=-1)
    assert (blends == 2).any() and (blends == 3).any()
    terms = diffusion_terms(fits)
    rng = np.random.default_rng(4)
    e = (rng.random((192, 192, 3)) * maps.coverage[..., None]).astype(np.float32)
    layouts = [DiffusionLayout(open_device(), maps.mm_per_texel_u, maps.mm_per_texel_v,
                               maps.coverage, maps.region_weights, texel_regions=regions)
               for regions in (None, maps.texel_regions)]
    assert not layouts[0].by_triangle and layouts[0].region_weights is not None
    assert layouts[1].by_triangle and layouts[1].region_weights is None
    want, got = (diffuse_prepared(layout, e, terms.variances_mm2, terms.weights)[0]
                 for layout in layouts)
    assert float(np.abs(want).max()) > 0
    np.testing.assert_allclose(got, want, rtol=5e-4, atol=1e-6)
    # the regions matter here: one profile for all (the first's) is far from either
    one = diffuse_prepared(layouts[0], e, terms.variances_mm2,
                           np.broadcast_to(terms.weights[:1], terms.weights.shape))[0]
    assert float(np.abs(one - want).max()) > 100 * float(np.abs(got - want).max())
    # a render's last frame lets the maps' own go; what they are made from stays
    let_go = maps.without_surface(keep_regions=False)
    assert let_go.region_weights is None and let_go.texel_regions is maps.texel_regions
