"""Diffusion: OpenCL blur vs float64 reference; the profile reproduced in mm."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.diffusion import OpenCLBlur, blur_reference, diffuse
from pipeline.profiles import fit_error_eq2c, sum_of_gaussians
from pipeline.reference_data import DEON_2007_SKIN


def test_opencl_matches_float64_reference() -> None:
    rng = np.random.default_rng(0)
    h, w = 40, 56
    image = rng.random((h, w, 4)).astype(np.float32)
    sigma_u = rng.uniform(0.1, 6.0, (h, w))
    sigma_v = rng.uniform(0.1, 6.0, (h, w))
    coverage = (rng.random((h, w)) > 0.15).astype(np.float32)
    ours = OpenCLBlur(coverage).blur(image, sigma_u, sigma_v)
    ref = blur_reference(image, sigma_u, sigma_v, coverage)
    np.testing.assert_allclose(ours, ref, rtol=1e-5, atol=1e-6)


def test_constant_field_stays_constant_at_chart_borders() -> None:
    h, w = 32, 32
    coverage = np.zeros((h, w), np.float32)
    coverage[4:28, 6:20] = 1.0
    image = np.ones((h, w, 4), np.float32)
    out = OpenCLBlur(coverage).blur(image, np.full((h, w), 5.0), np.full((h, w), 5.0))
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


def test_energy_is_conserved_away_from_borders() -> None:
    v = np.array([0.05, 0.5])
    w = np.array([[0.4, 0.5, 0.6], [0.6, 0.5, 0.4]])
    _, got, stats = _pencil(121, 0.05, 0.05, v, w)
    total = got.sum(axis=0) * 0.05 * 0.05
    np.testing.assert_allclose(total, 1.0, rtol=5e-3)
    assert stats.passes == 4


def test_zero_weight_terms_are_skipped() -> None:
    v = np.array([0.0004, 0.2, 1.0])
    w = np.array([[0.5, 0.5, 0.5], [0.0, 0.0, 0.0], [0.5, 0.5, 0.5]])
    _, _, stats = _pencil(41, 0.1, 0.1, v, w)
    assert any("zero weight" in s for s in stats.skipped)
    assert any("narrower than a texel" in s for s in stats.skipped)
