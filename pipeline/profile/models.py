"""Radial diffusion profiles R(r) and the paper's fit error, one function per method.

Every profile is a function of the radius in mm from the entry point and returns the
exitant radiant exitance per unit incident flux (mm^-2), so that its integral over the
plane, 2 pi \\int R(r) r dr, is the total diffuse reflectance.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from .reference_data import ScatteringCoefficients

FloatArray = NDArray[np.float64]


def gaussian_2d(variance_mm2: ArrayLike, radius_mm: ArrayLike) -> FloatArray:
    """Normalised 2D Gaussian G(v, r) = exp(-r^2 / (2 v)) / (2 pi v).

    d'Eon, Luebke, Enderton, EGSR 2007; the convention behind Park & Oh 2009, eq. 1.
    Broadcasts ``variance_mm2`` against ``radius_mm``. Integrates to 1 over the plane.
    """
    v = np.asarray(variance_mm2, dtype=np.float64)
    r = np.asarray(radius_mm, dtype=np.float64)
    return np.exp(-(r * r) / (2.0 * v)) / (2.0 * np.pi * v)


def sum_of_gaussians(
    variances_mm2: ArrayLike, weights: ArrayLike, radius_mm: ArrayLike
) -> FloatArray:
    """Park & Oh 2009, eq. 1: f(r) = sum_i w_i G(v_i, r), per colour channel.

    ``variances_mm2`` is (k,), ``weights`` is (k,) or (k, C); returns (n,) or (n, C).
    """
    v = np.asarray(variances_mm2, dtype=np.float64).reshape(-1)
    w = np.asarray(weights, dtype=np.float64)
    basis = gaussian_2d(v[None, :], np.asarray(radius_mm, dtype=np.float64).reshape(-1, 1))
    return basis @ w


def ring_widths_mm(radius_mm: ArrayLike) -> FloatArray:
    """The ``dr`` of eq. 2: each sample's share of the radial axis (midpoint rule).

    Handles non-uniform sampling; the first and last samples own half an interval.
    """
    r = np.asarray(radius_mm, dtype=np.float64)
    if r.size < 2:
        return np.ones_like(r)
    edges = np.concatenate(([r[0]], 0.5 * (r[1:] + r[:-1]), [r[-1]]))
    return np.diff(edges)


def disk_radius_mm(radius_mm: ArrayLike) -> float:
    """Outer edge of the disk that ring samples at ``radius_mm`` cover: half a spacing
    beyond the last ring (the rings' edges lie midway between samples)."""
    r = np.asarray(radius_mm, dtype=np.float64)
    return float(r[-1] + 0.5 * (r[-1] - r[-2]))


def fit_error_eq2c(
    radius_mm: ArrayLike, measured: ArrayLike, fitted: ArrayLike
) -> FloatArray:
    """Park & Oh 2009, eq. 2c: relative, r-weighted RMS error of a fitted profile.

    f = sqrt(sum r dr (p - f)^2) / sqrt(sum r dr f^2), per channel (last axis).
    Returns 0 for a perfect fit; ``inf`` where the fitted profile is identically zero.
    """
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(measured, dtype=np.float64)
    f = np.asarray(fitted, dtype=np.float64)
    w = (r * ring_widths_mm(r)).reshape((-1,) + (1,) * (p.ndim - 1))
    num = np.sqrt(np.sum(w * (p - f) ** 2, axis=0))
    den = np.sqrt(np.sum(w * f**2, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.inf)


def expected_error_eq2c(radius_mm: ArrayLike, values: ArrayLike, stddev: ArrayLike
                        ) -> FloatArray:
    """The eq. 2c error a profile's own noise gives it against the true one: per channel
    sqrt(sum r dr s^2) / sqrt(sum r dr p^2), for independent samples of standard
    deviation s (Park & Oh 2009, eq. 2c, in expectation). Biases are not in it."""
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64)
    s = np.asarray(stddev, dtype=np.float64)
    w = (r * ring_widths_mm(r)).reshape((-1,) + (1,) * (p.ndim - 1))
    den = np.sqrt(np.sum(w * p**2, axis=0))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, np.sqrt(np.sum(w * s**2, axis=0)) / np.where(den > 0, den,
                                                                              1.0), np.inf)


def total_reflectance_numeric(radius_mm: ArrayLike, profile: ArrayLike) -> FloatArray:
    """2 pi \\int R(r) r dr by the trapezoid rule over the sampled radii (per channel)."""
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(profile, dtype=np.float64)
    return 2.0 * np.pi * np.trapezoid(p * r.reshape((-1,) + (1,) * (p.ndim - 1)), r, axis=0)


def _diffuse_fresnel_reflectance(eta: float) -> float:
    # Egan & Hilgeman's polynomial fit, as used by Jensen et al. 2001, eq. 5.
    return -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta


def dipole_profile(radius_mm: ArrayLike, coefficients: ScatteringCoefficients) -> FloatArray:
    """Jensen, Marschner, Levoy, Hanrahan 2001, eq. 4: the dipole diffusion profile R_d(r).

    Written in the corrected form (Jensen & Buhler 2002) whose integral equals
    :func:`dipole_total_reflectance`. Returns (n, 3) in mm^-2 for RGB.
    """
    r = np.asarray(radius_mm, dtype=np.float64).reshape(-1, 1)
    s_sp = np.asarray(coefficients.sigma_s_prime, dtype=np.float64)
    s_a = np.asarray(coefficients.sigma_a, dtype=np.float64)
    s_tp = s_a + s_sp
    alpha_p = s_sp / s_tp
    s_tr = np.sqrt(3.0 * s_a * s_tp)
    diffusion = 1.0 / (3.0 * s_tp)
    f_dr = _diffuse_fresnel_reflectance(coefficients.eta)
    a = (1.0 + f_dr) / (1.0 - f_dr)
    z_r = 1.0 / s_tp
    z_v = z_r + 4.0 * a * diffusion
    d_r = np.sqrt(r * r + z_r * z_r)
    d_v = np.sqrt(r * r + z_v * z_v)
    real = z_r * (1.0 + s_tr * d_r) * np.exp(-s_tr * d_r) / d_r**3
    virtual = z_v * (1.0 + s_tr * d_v) * np.exp(-s_tr * d_v) / d_v**3
    return alpha_p / (4.0 * np.pi) * (real + virtual)


def dipole_total_reflectance(coefficients: ScatteringCoefficients) -> FloatArray:
    """Jensen et al. 2001, eq. 5: closed-form total diffuse reflectance of the dipole (RGB)."""
    s_sp = np.asarray(coefficients.sigma_s_prime, dtype=np.float64)
    s_a = np.asarray(coefficients.sigma_a, dtype=np.float64)
    alpha_p = s_sp / (s_a + s_sp)
    f_dr = _diffuse_fresnel_reflectance(coefficients.eta)
    a = (1.0 + f_dr) / (1.0 - f_dr)
    root = np.sqrt(3.0 * (1.0 - alpha_p))
    return alpha_p / 2.0 * (1.0 + np.exp(-4.0 / 3.0 * a * root)) * np.exp(-root)


def burley_scaling_searchlight(albedo: ArrayLike) -> FloatArray:
    """Christensen & Burley 2015, eq. 6: s = 1.85 - A + 7 |A - 0.8|^3 (mean-free-path fit)."""
    a = np.asarray(albedo, dtype=np.float64)
    return 1.85 - a + 7.0 * np.abs(a - 0.8) ** 3


def burley_profile(
    radius_mm: ArrayLike, albedo: ArrayLike, mean_free_path_mm: ArrayLike
) -> FloatArray:
    """Christensen & Burley 2015, eq. 3: R(r) = A (e^{-r/d} + e^{-r/(3 d)}) / (8 pi d r).

    d = l / s with l the mean free path and s from :func:`burley_scaling_searchlight`.
    ``albedo`` and ``mean_free_path_mm`` broadcast per channel. Integrates to A over the
    plane. Singular at r = 0 (returns inf there).
    """
    r = np.asarray(radius_mm, dtype=np.float64).reshape(-1, 1)
    a = np.atleast_1d(np.asarray(albedo, dtype=np.float64))
    mfp = np.atleast_1d(np.asarray(mean_free_path_mm, dtype=np.float64))
    d = mfp / burley_scaling_searchlight(a)
    with np.errstate(divide="ignore"):
        return a * (np.exp(-r / d) + np.exp(-r / (3.0 * d))) / (8.0 * np.pi * d * r)
