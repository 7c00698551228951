"""Radial diffusion profiles R(r) and the paper's fit error, one function per method.

Every profile is a function of the radius in mm from the entry point and returns the
exitant radiant exitance per unit incident flux (mm^-2), so that its integral over the
plane, 2 pi \\int R(r) r dr, is the total diffuse reflectance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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


def ring_edges_mm(radius_mm: ArrayLike) -> FloatArray:
    """The outer edge of each sample's ring (edges midway between samples, the last
    :func:`disk_radius_mm`)."""
    r = np.asarray(radius_mm, dtype=np.float64)
    if r.size == 1:
        return np.array([disk_radius_mm(np.array([0.0, r[0]]))])
    return np.concatenate([0.5 * (r[1:] + r[:-1]), [disk_radius_mm(r)]])


def ring_areas_mm2(radius_mm: ArrayLike) -> FloatArray:
    """The area of the ring each sample stands for, from 0 to :func:`disk_radius_mm`
    (:func:`ring_edges_mm`; their sum is the measured disk)."""
    return np.pi * np.diff(np.concatenate([[0.0], ring_edges_mm(radius_mm)]) ** 2)


def disk_flux(radius_mm: ArrayLike, values: ArrayLike) -> FloatArray:
    """2 pi int_0^R p(r) r dr over the measured disk (R = :func:`disk_radius_mm`), per
    channel: a monotone cubic through the samples (PCHIP, Fritsch & Carlson 1980),
    integrated by 3-point Gauss-Legendre per interval (exact for its quartic r p),
    constant inside the first sample and beyond the last. The ring-area rule
    (:func:`ring_areas_mm2`, the sample's value over the annulus around it) reads a
    core 2.3 pixels wide in sigma 0.5-0.7% high on 1 px rings; this, 1-2e-4."""
    from scipy.interpolate import PchipInterpolator  # lazy: 0.3 s to import

    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64).reshape(r.size, -1)
    if r.size < 2:
        return np.pi * disk_radius_mm(np.array([0.0, r[0]])) ** 2 * p[0]
    t, w = np.polynomial.legendre.leggauss(3)
    a, b = r[:-1, None], r[1:, None]
    x = 0.5 * (a + b) + 0.5 * (b - a) * t[None, :]
    values_x = PchipInterpolator(r, p, axis=0)(x.reshape(-1)).reshape(*x.shape, -1)
    inside = np.einsum("nk,nkc->c", 0.5 * (b - a) * w[None, :] * x, values_x)
    edge = disk_radius_mm(r)
    return 2.0 * np.pi * inside + np.pi * (r[0] ** 2 * p[0] + (edge**2 - r[-1] ** 2) * p[-1])


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
"""The outer part of the measured radii (here 40%) that the far-field tail models are
fitted on, and all of them are compared on."""
TAIL_DIPOLE_FRACTION = 0.7
"""The outer part the diffusion dipole is fitted on: it holds from about the depth of
its real source outward, and needs the bend where that source stops dominating."""
TAIL_MIN_SAMPLES = 5
TAIL_MIN_UNCERTAINTY = 0.1
"""The extrapolated share is known to no better than this fraction of itself."""
TAIL_MIN_SIGMA_TR = 0.02
"""The dipole's effective transport coefficient s = sqrt(3 sigma_a sigma_t') is kept above
this (per mm): skin lies at 0.1-1.6, Jensen et al. 2001's marble and whole milk at
0.05-0.3; a fit that drifts below reads a tail that hardly decays."""
TAIL_MAX_SHARE = 0.5
"""A model that puts more than this share of the plane's flux beyond the image is no
extrapolation anyone should trust: it is left out (and an image that small is warned
of: see ingest's TAIL_WARN_FRACTION)."""
TAIL_MAX_NFEV = 60
"""Residual evaluations a dipole fit may spend from one start (a tail that is no dipole,
such as a Gaussian's, otherwise takes hundreds for no better answer)."""
TAIL_SUPPORT_AIC = 10.0
"""Models within this AIC of the best still have support (Burnham & Anderson 2002: beyond
10, essentially none); their disagreement with the best is the tail's uncertainty."""


@dataclass(frozen=True)
class TailExtrapolation:
    """Per channel: the model the measured tail follows, the flux beyond the measured
    disk (2 pi int_R^inf p r dr, in the profile's units) and its share of the plane's
    flux."""

    model: tuple[str, ...]
    """Per channel: a key of :data:`TAIL_MODELS`, "dipole", "dipole+mix" or "none"."""
    flux_beyond: FloatArray
    fraction_beyond: FloatArray
    scale_uncertainty: FloatArray
    """How far the plane's flux is known, relative: the largest difference between the
    best model's share and that of a model within :data:`TAIL_SUPPORT_AIC` of it, at
    least :data:`TAIL_MIN_UNCERTAINTY` of the share (an error of the profile's scale,
    which is its eq. 2c error one for one)."""


def _exp1(x: float) -> float:
    """The exponential integral E1(x) (scipy.special, imported here: 0.14 s of every
    command's start, a render's included, for the one tail model that uses it)."""
    from scipy import special

    return float(special.exp1(x))


TAIL_MODELS = {
    # name: (power k of r in p = A exp(c1 x) / r^k, x = r^2 or r, flux beyond R)
    "gaussian": (0, 2, lambda amp, c1, edge: 2 * math.pi * amp * (-0.5 / c1)
                 * math.exp(c1 * edge**2)),
    "exponential": (0, 1, lambda amp, c1, edge: 2 * math.pi * amp * (-1 / c1)
                    * (edge - 1 / c1) * math.exp(c1 * edge)),
    "exponential/r": (1, 1, lambda amp, c1, edge: 2 * math.pi * amp * (-1 / c1)
                      * math.exp(c1 * edge)),
    "exponential/r^2": (2, 1, lambda amp, c1, edge: 2 * math.pi * amp
                        * _exp1(-c1 * edge)),
}
"""Tail models fitted as straight lines in log space: a Gaussian (the sum-of-Gaussians
model's widest term), an exponential, and exp(-s r) / r^k with k = 1, 2 (the diffusion
far field in and out of the plane). The diffusion dipole itself, "dipole", is fitted
apart (:func:`dipole_tail_shape`)."""


def dipole_tail_shape(radius_mm: ArrayLike, sigma_tr: float, z_r: float, z_v: float
                      ) -> FloatArray:
    """The shape of Jensen et al. 2001's dipole profile (eq. 4 less its constant):
    z_r (1 + s d_r) e^(-s d_r) / d_r^3 + z_v (1 + s d_v) e^(-s d_v) / d_v^3 with
    d = sqrt(r^2 + z^2), for an effective transport coefficient s and the real and
    virtual sources' depths z_r < z_v (mm)."""
    r = np.asarray(radius_mm, dtype=np.float64)
    d_r, d_v = np.sqrt(r * r + z_r * z_r), np.sqrt(r * r + z_v * z_v)
    return (z_r * (1 + sigma_tr * d_r) * np.exp(-sigma_tr * d_r) / d_r**3
            + z_v * (1 + sigma_tr * d_v) * np.exp(-sigma_tr * d_v) / d_v**3)


def dipole_tail_flux(edge_mm: ArrayLike, sigma_tr: float, z_r: float, z_v: float
                     ) -> FloatArray:
    """2 pi int_R^inf r (:func:`dipole_tail_shape`) dr in closed form, for each edge R:
    with r dr = d dd, each source gives 2 pi z e^(-s d) / d at d = sqrt(R^2 + z^2) (the
    antiderivative of (1 + s d) e^(-s d) / d^2 is -e^(-s d) / d)."""
    d_r, d_v = np.hypot(edge_mm, z_r), np.hypot(edge_mm, z_v)
    return 2 * math.pi * (z_r * np.exp(-sigma_tr * d_r) / d_r
                          + z_v * np.exp(-sigma_tr * d_v) / d_v)


@dataclass(frozen=True)
class _Dipoles:
    """A tail as a non-negative sum of dipole shapes (:func:`dipole_tail_shape`): the
    channel's own first, then any others' (fixed)."""

    amplitudes: FloatArray
    shapes: tuple[tuple[float, float, float], ...]
    """(s, z_r, z_v) per shape."""

    def values(self, radius_mm: FloatArray) -> FloatArray:
        return sum(a * dipole_tail_shape(radius_mm, *sh)
                   for a, sh in zip(self.amplitudes, self.shapes, strict=True))

    def flux_beyond(self, edge_mm: float) -> float:
        return float(sum(a * dipole_tail_flux(edge_mm, *sh)
                         for a, sh in zip(self.amplitudes, self.shapes, strict=True)))


def _fit_dipoles(r: FloatArray, p: FloatArray, sigma: FloatArray,
                 others: Sequence[tuple[float, float, float]] = (),
                 start: tuple[float, float, float] | None = None) -> _Dipoles | None:
    """A dipole of the channel's own (s, z_r, z_v free: log parameters) plus non-negative
    amounts of ``others`` (fixed shapes), fitted to (r, p) by least squares in units of
    sigma: the amounts solved exactly (NNLS on unit columns) at each step; starts from
    the four best of a coarse grid (s 0.1-3 per mm, z_r 0.1-3 mm, z_v - z_r 1-9 z_r), or
    from ``start`` and the grid's best. None when no start converges to a positive own
    amplitude."""
    from scipy.optimize import least_squares, nnls  # lazy: 0.50 s to import

    w = 1.0 / sigma
    fixed = [dipole_tail_shape(r, *o) * w for o in others]
    lower = [math.log(TAIL_MIN_SIGMA_TR), -8.0, -8.0]

    def params(x: FloatArray) -> tuple[float, float, float]:
        z_r = math.exp(x[1])
        return math.exp(x[0]), z_r, z_r + math.exp(x[2])

    def amounts(x: FloatArray) -> tuple[FloatArray, FloatArray]:
        cols = np.stack([dipole_tail_shape(r, *params(x)) * w, *fixed], axis=1)
        norm = np.linalg.norm(cols, axis=0)
        if not (np.all(np.isfinite(cols)) and np.all(norm > 0)):
            return np.zeros(cols.shape[1]), np.full(r.size, np.inf)
        a, _ = nnls(cols / norm, p * w)
        return a / norm, cols @ (a / norm) - p * w

    def resid(x: FloatArray) -> FloatArray:
        return amounts(x)[1]

    best = None
    with np.errstate(over="ignore", under="ignore", invalid="ignore", divide="ignore"):
        grid = [np.log([s0, z0, f * z0]) for s0 in (0.1, 0.3, 1.0, 3.0)
                for z0 in (0.1, 0.3, 1.0, 3.0) for f in (1.0, 3.0, 9.0)]
        costs = [float(np.sum(resid(x) ** 2)) for x in grid]
        # from a given start (the channel's dipole alone) one grid start is enough
        best_grid = np.argsort(np.nan_to_num(costs, nan=np.inf))[:4 if start is None else 1]
        starts = [grid[i] for i in best_grid]
        if start is not None:
            starts.insert(0, np.log([start[0], start[1], start[2] - start[1]]))
        for x0 in starts:
            try:
                res = least_squares(resid, np.clip(x0, lower, 5.0), max_nfev=TAIL_MAX_NFEV,
                                    bounds=(lower, [5.0] * 3))
            except ValueError:
                continue
            if np.isfinite(res.cost) and (best is None or res.cost < best.cost):
                best = res
    if best is None:
        return None
    amp, _ = amounts(best.x)
    return _Dipoles(amp, (params(best.x), *others)) if amp[0] > 0 else None


def _tail_candidates(r: FloatArray, p: FloatArray, sigma: FloatArray, edge_mm: float,
                     own: _Dipoles | None = None,
                     others: Sequence[tuple[float, float, float]] = (),
                     disk: float | None = None) -> list[tuple[float, str, float]]:
    """(AIC, model, flux beyond ``edge_mm``) of every tail model that decays, for one
    channel's samples in the outer :data:`TAIL_DIPOLE_FRACTION`: :data:`TAIL_MODELS`
    fitted on the outer :data:`TAIL_OUTER_FRACTION` as ln(p r^k) against r^2 or r,
    weighted by p / sigma (the error of ln p is sigma / p); the dipole (``own``, or
    fitted here) on all of them; and, given ``others`` (the other channels' dipole
    shapes), "dipole+mix": the own dipole refitted with non-negative amounts of
    theirs, for a camera channel whose band holds some of another's longer tail (P3's
    green holds 3% of Rec.709's red, which dominates beyond the image). Each compared
    on the outer TAIL_OUTER_FRACTION by AIC = chi^2 + 2 x parameters (Akaike 1974);
    given the measured ``disk`` flux, those that would put more than
    :data:`TAIL_MAX_SHARE` of the plane's flux beyond the image are left out."""
    far = r >= (1.0 - TAIL_OUTER_FRACTION) * edge_mm
    rf, pf, sf = r[far], p[far], sigma[far]
    fits: list[tuple[float, str, float]] = []
    if rf.size >= TAIL_MIN_SAMPLES:
        w = pf / sf
        for model, (k, power, flux_of) in TAIL_MODELS.items():
            x = rf**power
            a = np.stack([np.ones_like(x), x], axis=1) * w[:, None]
            (c0, c1), *_ = np.linalg.lstsq(a, np.log(pf * rf**k) * w, rcond=None)
            if not c1 < 0:
                continue  # no decay: nothing to extrapolate with this model
            fitted = np.exp(c0 + c1 * x) / rf**k
            chi2 = float(np.sum(((fitted - pf) / sf) ** 2))
            fits.append((chi2 + 4.0, model, flux_of(math.exp(c0), c1, edge_mm)))
    own = own if own is not None else _fit_dipoles(r, p, sigma)
    candidates = [("dipole", own)]
    if own is not None and others:
        candidates.append(("dipole+mix", _fit_dipoles(r, p, sigma, others, own.shapes[0])))
    for name, dip in candidates:
        if dip is not None and rf.size:
            chi2 = float(np.sum(((dip.values(rf) - pf) / sf) ** 2))
            fits.append((chi2 + 2.0 * (3 + len(dip.shapes)), name, dip.flux_beyond(edge_mm)))
    if disk is not None:  # a tail holding most of the plane's light is not believed
        fits = [f for f in fits if f[2] <= TAIL_MAX_SHARE / (1.0 - TAIL_MAX_SHARE) * disk]
    return sorted(fits)


def extrapolated_tail(radius_mm: ArrayLike, values: ArrayLike,
                      stddev: ArrayLike | None = None,
                      usable: ArrayLike | None = None) -> TailExtrapolation:
    """The flux of a radial profile beyond its measured disk (:func:`disk_radius_mm`),
    from the measured tail: the model of :func:`_tail_candidates` with the smallest AIC,
    on the samples at least 3 standard deviations above zero (1% of the value where
    none is given) and ``usable`` (where given: samples a caller trusts, e.g. those its
    single pixels resolve), integrated analytically to infinity; every channel's own
    dipole is fitted first, so that each may hold some of the others' ("dipole+mix"). The
    uncertainty is the disagreement of the models that still have support
    (:data:`TAIL_SUPPORT_AIC`). A channel with fewer than :data:`TAIL_MIN_SAMPLES` such
    samples, or no decaying tail, gets none."""
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64).reshape(r.size, -1)
    s = np.abs(p) * 0.01 if stddev is None else \
        np.asarray(stddev, dtype=np.float64).reshape(p.shape)
    edge = disk_radius_mm(r)
    outer = r >= (1.0 - TAIL_DIPOLE_FRACTION) * edge
    disk = disk_flux(r, p)
    ok = np.ones(p.shape, bool) if usable is None else \
        np.asarray(usable, dtype=bool).reshape(p.shape)
    uses = [outer & ok[:, c] & (p[:, c] > 3 * s[:, c]) & (s[:, c] > 0)
            for c in range(p.shape[1])]
    enough = [int(u.sum()) >= TAIL_MIN_SAMPLES for u in uses]
    # each channel's own dipole first: the shapes the others may hold some of
    dipoles = [_fit_dipoles(r[u], p[u, c], s[u, c]) if ok else None
               for c, (u, ok) in enumerate(zip(uses, enough, strict=True))]
    models, beyond, spread = [], [], []
    for c, (use, ok) in enumerate(zip(uses, enough, strict=True)):
        others = [d.shapes[0] for k, d in enumerate(dipoles) if k != c and d is not None]
        fits = _tail_candidates(r[use], p[use, c], s[use, c], edge, dipoles[c], others,
                                float(disk[c])) if ok else []
        models.append(fits[0][1] if fits else "none")
        beyond.append(fits[0][2] if fits else 0.0)
        supported = [f for aic, _, f in fits if aic - fits[0][0] <= TAIL_SUPPORT_AIC]
        spread.append(max(abs(f - fits[0][2]) for f in supported) if fits else 0.0)
    flux_beyond = np.asarray(beyond)
    total = np.maximum(disk + flux_beyond, 1e-300)
    share = flux_beyond / total
    return TailExtrapolation(tuple(models), flux_beyond, share,
                             np.maximum(np.asarray(spread) / total,
                                        TAIL_MIN_UNCERTAINTY * share))
