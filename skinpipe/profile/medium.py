"""The homogeneous medium a measured profile implies, for renderers that take one.

Production renderers (and OpenPBR, §"Subsurface" of its specification) describe skin as a
semi-infinite homogeneous medium: per channel an extinction mu_t = 1 / l (l the mean free
path) and a single-scattering albedo alpha, with one Henyey-Greenstein anisotropy g,
behind an index-matched boundary (the assumption of the albedo formula the specification
quotes). This module inverts a measured pencil-beam profile to (alpha, l, g):

1. **alpha from the total reflectance.** The paper measures the exit radiance seen from
   straight above under a normal pencil; times pi, summed over the surface, that is the
   total reflectance R the albedo texture carries. For an isotropic half space it is
   exactly R(alpha) = alpha H(alpha, 1)^2 / 8 (Chandrasekhar 1960, eq. IV.14 at
   mu = mu0 = 1; H his function, eq. V.41); for 0 < g <= 0.7 it is tabulated by
   adding-doubling (pencil_reflectance_table.py, from tools/tabulate_pencil_reflectance.py),
   at 0.8 and 0.9 (skin's own g, where adding-doubling's quadrature goes unstable) by the
   light tracer that traces the shape (pencil_profile_table.py). Each is inverted by
   bisection.
2. **l and g from the profile's shape.** Of R, the single scattering of the pencil is
   alpha p_g(-1) pi / 2, all of it at the entry point (the pencil goes straight down): a
   share of 1 / H(alpha, 1)^2 at g = 0, 1-4% at 0.7, 0.6-1% at 0.9. The rest is multiply
   scattered, shaped as the multiply scattered light of a half space of the same g
   tallied by the tests' light tracer (pencil_profile_table.py, from
   tools/tabulate_pencil_profile.py): the medium's own shape, so that the model's
   residual is what a path tracer shows of the medium written. (Closed forms are not:
   Christensen & Burley 2015 and the diffusion dipole, at the similarity relation's
   reduced albedo and length, matched the sample captures' edges to 1-2% with media
   that, traced, missed them by 3.5-7.7%.) l is fitted per channel so that the largest
   difference of the model's edge-spread function (:mod:`.edge`) from the measured one
   is least (a coarse scan over four decades first: a far too long path makes a flat
   disc over the measured radii, a second minimum); g is the one whose largest
   difference over the channels is least. The measured entry spike is what fixes g:
   skin1's (a fifth to a half of its light) gives g = 0, a diffusion-shaped capture with
   none the largest tried, 0.9.
3. **OpenPBR's colour.** The specification's alpha(C) is the inverse of van de Hulst's
   C(alpha) = (1 - s)(1 - 0.139 s) / (1 + 1.17 s), s = sqrt((1 - alpha) / (1 - alpha g))
   (Kulla & Conty 2017); a renderer following it recovers alpha from C = C(alpha). That C
   is the albedo under uniform light (bi-hemispherical), not the pencil's R: 0.625
   against 0.545 for skin1's red.

Residuals are reported as any fit's: eq. 2c of the model's ring means against the
measured samples and the edge-spread error (largest difference of the edge functions
beyond the central two rings, share of the plateau).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import PchipInterpolator, make_smoothing_spline
from scipy.optimize import brentq, minimize_scalar

from ..errors import InputError
from . import pencil_profile_table as PROFILE
from . import pencil_reflectance_table as TABLE
from .edge import ring_areas_beyond
from .models import (
    fit_error_eq2c,
    ring_areas_mm2,
    ring_edges_mm,
)

FloatArray = NDArray[np.float64]

_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(64)
_MU, _W = 0.5 * (_NODES + 1.0), 0.5 * _WEIGHTS
_PROFILE_S = np.asarray(PROFILE.S_GRID)
_PROFILE_RADII = np.asarray(PROFILE.RADII)
_PROFILE_BEYOND = np.asarray(PROFILE.BEYOND)
EDGE_POSITIONS = 100
"""Edge positions the shape fit compares, log-spaced (the reported error uses all)."""
LENGTH_SCAN = 49
"""Mean free paths scanned (log-spaced, over a factor 10^4) before the search refines."""


def chandrasekhar_h(albedo: float, mu: ArrayLike) -> FloatArray:
    """Chandrasekhar's H(mu) for isotropic scattering of single-scattering ``albedo``:
    1 / H(mu) = sqrt(1 - a) + (a / 2) int_0^1 mu' H(mu') / (mu + mu') dmu'
    (Chandrasekhar 1960, eq. V.41) on 64 Gauss-Legendre nodes, solved by Newton's
    method from his approximation (1 + 2 mu) / (1 + 2 mu sqrt(1 - a)): plain iteration
    crawls as a -> 1."""
    a = float(albedo)
    root = math.sqrt(max(1.0 - a, 0.0))
    kernel = 0.5 * a * (_MU * _W)[None, :] / (_MU[:, None] + _MU[None, :])  # [j, i]
    h = (1.0 + 2.0 * _MU) / (1.0 + 2.0 * _MU * root)
    for _ in range(100):
        g = root + kernel @ h
        step = np.linalg.solve(np.diag(g) + h[:, None] * kernel, h * g - 1.0)
        h = h - step
        if np.max(np.abs(step)) < 1e-13:
            break
    m = np.asarray(mu, dtype=np.float64)
    return 1.0 / (root + 0.5 * a * (
        (_MU * h * _W)[:, None] / (m.reshape(1, -1) + _MU[:, None])).sum(axis=0)
    ).reshape(m.shape)


def henyey_greenstein(cos_theta: ArrayLike, g: ArrayLike) -> FloatArray:
    """p_g(cos Theta) = (1 - g^2) / (4 pi (1 + g^2 - 2 g cos Theta)^1.5), over the sphere."""
    c = np.asarray(cos_theta, dtype=np.float64)
    g = np.asarray(g, dtype=np.float64)
    return (1.0 - g * g) / (4.0 * math.pi * np.maximum(1.0 + g * g - 2.0 * g * c, 1e-12) ** 1.5)


def similarity_relation(albedo: ArrayLike, g: ArrayLike) -> tuple[Any, Any]:
    """van de Hulst's similarity relation: the isotropic medium a medium of albedo alpha
    and anisotropy g scatters like, as (alpha' = alpha (1 - g) / (1 - alpha g), and the
    factor 1 - alpha g that takes sigma_t to sigma_t' = 1 / l')."""
    a = albedo
    return a * (1.0 - g) / (1.0 - a * g), 1.0 - a * g


def pencil_reflectance(albedo: float) -> float:
    """R = alpha H(alpha, 1)^2 / 8: pi times the exit radiance seen from straight above,
    summed over the surface, per unit power of a normal pencil (index-matched, isotropic)."""
    return float(albedo * chandrasekhar_h(albedo, 1.0) ** 2 / 8.0)


def albedo_from_pencil_reflectance(reflectance: float) -> float:
    """The single-scattering albedo of the isotropic medium whose
    :func:`pencil_reflectance` is ``reflectance``. R reaches H(1, 1)^2 / 8 = 1.057 at
    alpha = 1: a conservative medium's pencil seen from above looks brighter than a
    Lambertian white, as its exit peaks at the normal."""
    shape = _shape(float(reflectance))
    if shape is None:
        top = float(_reflectance_over_s(0.0)(0.0))
        raise InputError(f"total reflectance {float(reflectance):g} is outside (0, "
                         f"{top:.4f}): no index-matched medium reflects that")
    return shape.albedo


def van_de_hulst_colour(albedo: ArrayLike, anisotropy: float = 0.0) -> FloatArray:
    """OpenPBR's subsurface colour of a medium: C = (1 - s)(1 - 0.139 s) / (1 + 1.17 s),
    s = sqrt((1 - alpha) / (1 - alpha g)) (OpenPBR 1.1, §Subsurface; van de Hulst)."""
    a = np.asarray(albedo, dtype=np.float64)
    s = np.sqrt((1.0 - a) / (1.0 - a * anisotropy))
    return (1.0 - s) * (1.0 - 0.139 * s) / (1.0 + 1.17 * s)


def albedo_from_van_de_hulst(colour: ArrayLike, anisotropy: float = 0.0) -> FloatArray:
    """What a renderer following OpenPBR derives from ``colour``: alpha = (1 - s^2) /
    (1 - g s^2), s = 4.09712 + 4.20863 C - sqrt(9.59217 + 41.6808 C + 17.7126 C^2)."""
    c = np.asarray(colour, dtype=np.float64)
    s = 4.09712 + 4.20863 * c - np.sqrt(9.59217 + 41.6808 * c + 17.7126 * c * c)
    return (1.0 - s * s) / (1.0 - anisotropy * s * s)


@dataclass(frozen=True)
class MediumEstimate:
    """Per channel (3,): the medium and how well its model reproduces the profile."""

    single_scattering_albedo: FloatArray
    mean_free_path_mm: FloatArray
    anisotropy: float
    """g of the Henyey-Greenstein phase function, one for all channels."""
    total_reflectance: FloatArray
    """R the medium was made to reflect (the pencil's, as the capture measures it)."""
    error_eq2c: FloatArray
    edge_error: FloatArray
    model: str = "traced"
    """The multiple-scattering shape the medium was matched with: the light tracer's."""

    @property
    def subsurface_colour(self) -> FloatArray:
        """OpenPBR's subsurface_color that makes a renderer derive this albedo."""
        return van_de_hulst_colour(self.single_scattering_albedo, self.anisotropy)


def _traced_ring_means(outer: FloatArray, albedo: float, mean_free_path_mm: float,
                       anisotropy: float = 0.0) -> FloatArray:
    """The multiply scattered light of an index-matched half space of Henyey-Greenstein
    ``anisotropy`` (one of the table's) as the light tracer tallies it
    (pencil_profile_table.py), normalised, averaged over each ring: its share beyond r
    interpolated in s = sqrt((1 - alpha) / (1 - alpha g)) and log r; inside the first
    radius the density is taken as flat, beyond the last there is none."""
    table = _PROFILE_BEYOND[PROFILE.ANISOTROPIES.index(anisotropy)]
    s = math.sqrt(max(1.0 - albedo, 0.0) / (1.0 - albedo * anisotropy))
    s = min(max(s, _PROFILE_S[0]), _PROFILE_S[-1])
    i = min(max(int(np.searchsorted(_PROFILE_S, s)) - 1, 0), _PROFILE_S.size - 2)
    f = (s - _PROFILE_S[i]) / (_PROFILE_S[i + 1] - _PROFILE_S[i])
    row = (1.0 - f) * table[i] + f * table[i + 1]
    r = np.concatenate([[0.0], outer]) / mean_free_path_mm
    first = _PROFILE_RADII[0]
    beyond = np.where(r < first, 1.0 - (1.0 - row[0]) * (r / first) ** 2,
                      np.interp(np.log(np.maximum(r, first)), np.log(_PROFILE_RADII), row,
                                right=0.0))
    return -np.diff(beyond) / (math.pi * np.diff(np.concatenate([[0.0], outer]) ** 2))


@dataclass(frozen=True)
class _Shape:
    """What fixes a medium's profile shape but its length: albedo alpha, anisotropy g
    and the single scattering's share of R."""

    albedo: float
    anisotropy: float
    single_share: float


@cache
def _reflectance_over_s(g: float) -> PchipInterpolator:
    """R against s = sqrt((1 - alpha) / (1 - alpha g)): Chandrasekhar's exact form at
    g = 0 (257 points, interpolated to 1e-8), the adding-doubling table to 0.7, the
    light tracer's beyond (relative to adding-doubling's 0.7, smoothed)."""
    if g == 0.0:
        s = np.linspace(0.0, 1.0, 257)
        return PchipInterpolator(s, [pencil_reflectance(1.0 - x * x) for x in s])
    if g in PROFILE.TRACED_REFLECTANCE:
        # each traced total carries about 1% noise at 0.9: their ratio to the last
        # adding-doubling row is smoothed (a penalised spline, its weight chosen by
        # generalised cross-validation), so that the inverted albedo does not follow it
        s = np.asarray(PROFILE.S_GRID)
        adding_doubling = _reflectance_over_s(TABLE.ANISOTROPIES[-1])
        ratio = make_smoothing_spline(
            s, np.asarray(PROFILE.TRACED_REFLECTANCE[g]) / adding_doubling(s))
        fine = np.linspace(s[0], s[-1], 257)
        return PchipInterpolator(fine, adding_doubling(fine) * ratio(fine))
    k = TABLE.ANISOTROPIES.index(g)
    return PchipInterpolator(TABLE.S_GRID, TABLE.REFLECTANCE[k])


def _shape(reflectance: float, g: float = 0.0) -> _Shape | None:
    """The medium of anisotropy ``g`` reflecting ``reflectance``, None if none does. Its
    single scattering is alpha p_g(-1) pi / 2 (the pencil's first collisions, all on the
    axis), the rest multiply scattered."""
    curve = _reflectance_over_s(g)
    low, high = float(curve.x[0]), float(curve.x[-1])
    if not float(curve(high)) < reflectance < float(curve(low)):
        return None
    root = float(brentq(lambda x: float(curve(x)) - reflectance, low, high, xtol=1e-13))
    a = (1.0 - root * root) / (1.0 - g * root * root)
    back = float(henyey_greenstein(-1.0, g))  # straight back up the pencil
    return _Shape(a, g, a * back * math.pi / 2.0 / reflectance)


def _ring_means(outer: FloatArray, shape: _Shape, mean_free_path_mm: float) -> FloatArray:
    """The medium's normalised profile averaged over each ring: its single scattering
    in the first, its multiply scattered light as traced."""
    ms = _traced_ring_means(outer, shape.albedo, mean_free_path_mm, shape.anisotropy)
    out = (1.0 - shape.single_share) * ms
    out[0] += shape.single_share / (math.pi * outer[0] ** 2)
    return out


ANISOTROPIES = PROFILE.ANISOTROPIES
"""The phase-function anisotropies g tried: g sets how much of the light the pencil's
single scattering sends straight back (its entry spike), from 1 / H(alpha, 1)^2 of R at
g = 0 to about 1% at 0.9 (skin's g is 0.8-0.9: Jacques et al. 1987)."""


def estimate_medium(radius_mm: ArrayLike, values: ArrayLike, total_reflectance: ArrayLike
                    ) -> MediumEstimate:
    """Invert a measured profile (``values`` (n, 3) at ``radius_mm``, any scale: only its
    shape is used) reflecting ``total_reflectance`` (3,) to a medium (see the module):
    per channel the mean free path for each g of :data:`ANISOTROPIES`, keeping the g
    (one for all channels, as OpenPBR has one) whose edges match best."""
    r = np.asarray(radius_mm, dtype=np.float64).reshape(-1)
    p = np.asarray(values, dtype=np.float64).reshape(r.size, -1)
    refl = np.broadcast_to(np.asarray(total_reflectance, dtype=np.float64), (p.shape[1],))
    if r.size < 3 or not np.all(np.isfinite(p)) or not np.all(np.diff(r) > 0):
        raise InputError("a medium needs at least 3 finite samples at increasing radii")
    outer = ring_edges_mm(r)
    area = ring_areas_mm2(r)
    central = outer[min(1, r.size - 1)] - 1e-12
    # E(t) + E(-t) is the total: the light beyond t >= 0, over the total, says it all.
    # The fit compares positions spaced evenly in log t (the entry's structure is within
    # a few rings); the reported error takes every ring edge.
    every = outer[outer >= central]
    want = np.geomspace(every[0], every[-1], EDGE_POSITIONS)
    beyond_every = ring_areas_beyond(r, every)
    beyond = beyond_every[np.unique(np.clip(np.searchsorted(every, want), 0, every.size - 1))]
    mean = p.clip(0).mean(axis=1)
    rms_mm = max(float(np.sqrt(np.sum(mean * r**3) / max(np.sum(mean * r), 1e-300))), 1e-3)
    bounds = (math.log(rms_mm / 100), math.log(rms_mm * 100))
    totals = np.maximum(area @ p, 1e-300)
    measured = beyond @ p / totals

    def fit(shape: _Shape | None, c: int) -> tuple[float, float, _Shape] | None:
        """(largest edge difference, mean free path, shape) of channel c's best fit."""
        if shape is None:
            return None

        def spread(log_l: float) -> FloatArray:
            ring_means = _ring_means(outer, shape, math.exp(log_l))
            return beyond @ ring_means / max(float(area @ ring_means), 1e-300) \
                - measured[:, c]

        def largest(log_l: float) -> float:
            """The largest difference, as reported and as a path tracer's image shows it."""
            return float(np.abs(spread(log_l)).max())

        # a coarse scan first: far too long a path gives a flat disc over the measured
        # radii, a second dip Brent's search alone can settle in (forward scattering)
        grid = np.linspace(*bounds, LENGTH_SCAN)
        k = int(np.argmin([largest(x) for x in grid]))
        near = (grid[max(k - 1, 0)], grid[min(k + 1, grid.size - 1)])
        best = minimize_scalar(largest, bounds=near, method="bounded",
                               options={"xatol": 1e-4})
        return largest(best.x), math.exp(best.x), shape

    for x in refl:
        albedo_from_pencil_reflectance(x)  # refuses what no medium reflects
    fits: dict[float, list[tuple[float, float, _Shape]]] = {}
    best = math.inf  # the least largest-channel error of the g fitted so far
    for g in ANISOTROPIES:
        shapes = [_shape(float(x), g) for x in refl]
        found: list[tuple[float, float, _Shape]] = []
        # the last channel first (blue: skin's shortest, the hardest edge), and a
        # channel as far off as the best g's worst means this g cannot win (an earlier
        # g wins a tie): its other channels are not fitted
        for c in reversed(range(len(shapes))):
            got = fit(shapes[c], c)
            if got is None or got[0] >= best:
                break
            found.insert(0, got)
        else:
            fits[g] = found
            best = min(best, max(f[0] for f in found))
    g_best = min(fits, key=lambda k: max(f[0] for f in fits[k]))
    albedo, mfp, err2c, edge = (np.empty(p.shape[1]) for _ in range(4))
    for c, (_, length, shape) in enumerate(fits[g_best]):
        albedo[c], mfp[c] = shape.albedo, length
        model = _ring_means(outer, shape, length)
        err2c[c] = float(fit_error_eq2c(r, p[:, c] / totals[c], model))
        edge[c] = float(np.abs(beyond_every @ model / (area @ model)
                               - beyond_every @ p[:, c] / totals[c]).max())
    return MediumEstimate(albedo, mfp, g_best, refl.copy(), err2c, edge)
