"""Radial diffusion profiles R(r) and the paper's fit error, one function per method.

Every profile is a function of the radius in mm from the entry point and returns the
exitant radiant exitance per unit incident flux (mm^-2), so that its integral over the
plane, 2 pi \\int R(r) r dr, is the total diffuse reflectance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

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


def ring_areas_mm2(radius_mm: ArrayLike) -> FloatArray:
    """The area of the ring each sample stands for: edges midway between samples, from
    0 to :func:`disk_radius_mm` (their sum is the measured disk)."""
    r = np.asarray(radius_mm, dtype=np.float64)
    edges = np.concatenate([[0.0], 0.5 * (r[1:] + r[:-1]), [disk_radius_mm(r)]])
    return np.pi * np.diff(edges**2)


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


TAIL_OUTER_FRACTION = 0.4
"""The outer part of the measured radii (here 40%) that the tail model is fitted on."""
TAIL_MIN_SAMPLES = 5
TAIL_RELATIVE_UNCERTAINTY = 1.0
"""How well the extrapolated tail is known: measured on the sample captures (diffusion
dipoles, 4 mm field), the extrapolated share was off by 6-84% of itself (red, 14-23%
of the light beyond the image: 6-35%; the lips' blue, 2.8%: 84%), so +-100%: a
factor of two."""


@dataclass(frozen=True)
class TailExtrapolation:
    """Per channel: the model the measured tail follows (a key of :data:`TAIL_MODELS`,
    or "none"), the flux beyond the measured disk (2 pi int_R^inf p r dr, in the
    profile's units) and its share of the plane's flux."""

    model: tuple[str, ...]
    flux_beyond: FloatArray
    fraction_beyond: FloatArray
    scale_uncertainty: FloatArray
    """How far the plane's flux is known, relative: :data:`TAIL_RELATIVE_UNCERTAINTY`
    of the extrapolated share (an error of the profile's scale, which is its eq. 2c
    error one for one)."""


TAIL_MODELS = {
    # name: (power k of r in p = A exp(c1 x) / r^k, x = r^2 or r, flux beyond R)
    "gaussian": (0, 2, lambda amp, c1, edge: 2 * math.pi * amp * (-0.5 / c1)
                 * math.exp(c1 * edge**2)),
    "exponential": (0, 1, lambda amp, c1, edge: 2 * math.pi * amp * (-1 / c1)
                    * (edge - 1 / c1) * math.exp(c1 * edge)),
    "exponential/r": (1, 1, lambda amp, c1, edge: 2 * math.pi * amp * (-1 / c1)
                      * math.exp(c1 * edge)),
    "exponential/r^2": (2, 1, lambda amp, c1, edge: 2 * math.pi * amp
                        * float(special.exp1(-c1 * edge))),
}
"""Tail models: a Gaussian (the sum-of-Gaussians model's widest term), an exponential,
and the diffusion dipole's far field, exp(-sigma_tr r) / r^k with k = 1 (in the plane)
to 2 (Jensen et al. 2001, eq. 5 for r >> z_r, z_v)."""


def _tail_flux(r: FloatArray, p: FloatArray, sigma: FloatArray, edge_mm: float
               ) -> tuple[str, float]:
    """(model, flux beyond ``edge_mm``) of one channel's outer samples: ln(p r^k) fitted
    against r^2 or r for each of :data:`TAIL_MODELS`, weighted by p / sigma (the error
    of ln p is sigma / p); the model with the smallest weighted residual among those
    that decay, integrated analytically from ``edge_mm`` to infinity."""
    fits: list[tuple[float, str, float]] = []
    w = p / sigma
    for model, (k, power, flux_of) in TAIL_MODELS.items():
        x = r**power
        y = np.log(p * r**k)
        a = np.stack([np.ones_like(x), x], axis=1) * w[:, None]
        (c0, c1), *_ = np.linalg.lstsq(a, y * w, rcond=None)
        if not c1 < 0:
            continue  # no decay: nothing to extrapolate with this model
        resid = float(np.sum((a @ np.array([c0, c1]) - y * w) ** 2))
        fits.append((resid, model, flux_of(math.exp(c0), c1, edge_mm)))
    if not fits:
        return "none", 0.0
    _, model, flux = min(fits)
    return model, flux


def extrapolated_tail(radius_mm: ArrayLike, values: ArrayLike,
                      stddev: ArrayLike | None = None) -> TailExtrapolation:
    """The flux of a radial profile beyond its measured disk (:func:`disk_radius_mm`),
    from the measured tail: :func:`_tail_flux` over the outer
    :data:`TAIL_OUTER_FRACTION` of the radii, on the samples at least 3 standard
    deviations above zero (1% of the value where none is given). A channel with fewer
    than :data:`TAIL_MIN_SAMPLES` such samples, or no decaying tail, gets none."""
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64).reshape(r.size, -1)
    s = np.abs(p) * 0.01 if stddev is None else \
        np.asarray(stddev, dtype=np.float64).reshape(p.shape)
    edge = disk_radius_mm(r)
    outer = r >= (1.0 - TAIL_OUTER_FRACTION) * edge
    disk = (p * ring_areas_mm2(r)[:, None]).sum(axis=0)
    models, beyond = [], []
    for c in range(p.shape[1]):
        use = outer & (p[:, c] > 3 * s[:, c]) & (s[:, c] > 0)
        model, flux = ("none", 0.0) if use.sum() < TAIL_MIN_SAMPLES else \
            _tail_flux(r[use], p[use, c], s[use, c], edge)
        models.append(model)
        beyond.append(flux)
    flux_beyond = np.asarray(beyond)
    share = flux_beyond / np.maximum(disk + flux_beyond, 1e-300)
    return TailExtrapolation(tuple(models), flux_beyond, share,
                             TAIL_RELATIVE_UNCERTAINTY * share)
