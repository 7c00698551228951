"""Light crossing the skin's surface: a smooth dielectric boundary of the skin's index
(Fresnel's unpolarised reflectance), and how deep light entering at an angle starts to
scatter (the diffusion dipole of Jensen et al. 2001).

A measured profile and its albedo are what a camera saw with light entering and leaving
at normal incidence. Light arriving at angle theta_i loses a Fresnel share F(theta_i)
at the surface instead of F(0): the entering light is weighted by

    T(theta_i) = (1 - F(theta_i)) / (1 - F(0)),

1 at normal incidence, so the measured albedo is not attenuated a second time. Leaving
towards the eye at theta_o it is weighted by T(theta_o) likewise.

Light refracted to theta_t (sin theta_t = sin theta_i / eta) meets its first scattering
nearer the surface, mu_t = cos theta_t times as deep, and more of it comes back out. In
the dipole model a point source at depth z sends 1/2 (e^(-sigma_tr z) + e^(-sigma_tr (z +
4 A D))) of its light out through the surface (Jensen et al. 2001, the integral of
eq. 4 over the plane); averaged over the first interaction's depth, exponential along
the refracted ray with reduced extinction sigma_t', that is proportional to
1 / (1 + s mu_t) with s = sigma_tr / sigma_t' = sqrt(3 (1 - alpha')). Relative to
normal incidence the diffuse light is therefore weighted by

    D(mu_t) = (1 + s) / (1 + s mu_t),

with the reduced albedo alpha' found from the skin's albedo by inverting the dipole's
total diffuse reflectance (Jensen et al. 2001, eq. 12 as given in pbrt). Index-matched
skin follows :mod:`.reflection_law` instead, which has single scattering's angles too.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...errors import InputError

SKIN_IOR = 1.4
"""The skin's refractive index where an asset gives none (Tuchin 2007: 1.36-1.45 for the
epidermis; the paper's specular uses 1.4)."""


def fresnel_dielectric(cos_i: ArrayLike, eta: float) -> NDArray[np.float64]:
    """Unpolarised reflectance of a smooth boundary, light from air into index ``eta``."""
    c = np.clip(np.abs(np.asarray(cos_i, dtype=np.float64)), 0.0, 1.0)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - c * c)) / eta
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin_t * sin_t))
    rs = (c - eta * cos_t) / np.maximum(c + eta * cos_t, 1e-300)
    rp = (eta * c - cos_t) / np.maximum(eta * c + cos_t, 1e-300)
    return 0.5 * (rs * rs + rp * rp)


def transmission(cos_i: ArrayLike, eta: float) -> NDArray[np.float64]:
    """T(theta) = (1 - F(theta)) / (1 - F(0)): the light that crosses the boundary at
    ``cos_i`` relative to normal incidence (0 below the horizon)."""
    c = np.asarray(cos_i, dtype=np.float64)
    t = (1.0 - fresnel_dielectric(c, eta)) / (1.0 - float(fresnel_dielectric(1.0, eta)))
    return np.where(c > 0, t, 0.0)


TABLE_SIZE = 256
"""Cosines in :func:`transmission_table` (linear interpolation in it: within 2e-4 of the
exact factor above 2 degrees from the horizon)."""


@lru_cache(maxsize=8)
def transmission_table(eta: float, n: int = TABLE_SIZE) -> NDArray[np.float32]:
    """:func:`transmission` at n cosines from 0 to 1, for the light-sampling kernel."""
    table = transmission(np.linspace(0.0, 1.0, n), eta).astype(np.float32)
    table.flags.writeable = False
    return table


def transmission_lookup(cos_i: ArrayLike, eta: float) -> NDArray[np.float32]:
    """:func:`transmission` as the light-sampling kernel reads it from the table (the
    samplers made in numpy read it so too: the same weights)."""
    table = transmission_table(float(eta))
    c = np.clip(np.asarray(cos_i, dtype=np.float32), 0.0, 1.0)
    x = c * np.float32(table.size - 1)
    j = np.minimum(x.astype(np.int32), table.size - 2)
    return table[j] + (x - j.astype(np.float32)) * (table[j + 1] - table[j])


def refracted_cos(cos_i: ArrayLike, eta: float) -> NDArray[np.float64]:
    """cos theta_t of light entering at ``cos_i`` (Snell's law)."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    return np.sqrt(np.maximum(0.0, 1.0 - (1.0 - c * c) / (eta * eta)))


def _diffuse_fresnel_a(eta: float) -> float:
    """A = (1 + F_dr) / (1 - F_dr), F_dr the diffuse Fresnel reflectance inside
    (Jensen et al. 2001's fit in eta)."""
    f_dr = -1.440 / eta**2 + 0.710 / eta + 0.668 + 0.0636 * eta
    return (1 + f_dr) / (1 - f_dr)


def total_reflectance(alpha_p: ArrayLike, eta: float) -> NDArray[np.float64]:
    """The dipole's total diffuse reflectance for reduced albedo ``alpha_p``: alpha'/2
    (1 + exp(-4/3 A sqrt(3 (1 - alpha')))) exp(-sqrt(3 (1 - alpha')))."""
    a = np.asarray(alpha_p, dtype=np.float64)
    root = np.sqrt(3.0 * (1.0 - a))
    return a / 2 * (1 + np.exp(-4.0 / 3.0 * _diffuse_fresnel_a(eta) * root)) * np.exp(-root)


@lru_cache(maxsize=8)
def _inverse_table(eta: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    alpha = 1.0 - np.geomspace(1e-7, 1.0, 4000)[::-1]
    return total_reflectance(alpha, eta), alpha


def reduced_albedo(albedo: ArrayLike, eta: float) -> NDArray[np.float64]:
    """alpha' whose dipole reflectance is ``albedo`` (monotone: interpolated in a table),
    clipped to the reflectances the dipole reaches."""
    reflectance, alpha = _inverse_table(float(eta))
    return np.interp(np.asarray(albedo, dtype=np.float64), reflectance, alpha)


@dataclass(frozen=True)
class SkinBoundary:
    """The boundary a skin mesh's light crosses: its index and, per channel, the reduced
    albedo its depth factor uses (from the mesh's mean albedo)."""

    eta: float = SKIN_IOR
    reduced_albedo: tuple[float, float, float] = (0.9, 0.9, 0.9)

    def __post_init__(self) -> None:
        if not (1.0 <= self.eta <= 3.0):
            raise InputError(f"the skin's refractive index must be 1-3, got {self.eta}")

    @classmethod
    def from_albedo(cls, albedo_rgb: ArrayLike, eta: float = SKIN_IOR) -> SkinBoundary:
        a = reduced_albedo(np.clip(np.asarray(albedo_rgb, dtype=np.float64), 0.0, 1.0), eta)
        return cls(float(eta), tuple(float(x) for x in a))  # type: ignore[arg-type]

    def depth_factor(self, cos_i: ArrayLike) -> NDArray[np.float32]:
        """D(mu_t) per channel (N, 3) for light arriving at ``cos_i`` (N,)."""
        s = np.sqrt(3.0 * (1.0 - np.asarray(self.reduced_albedo)))
        mu = refracted_cos(cos_i, self.eta)[:, None]
        return ((1.0 + s) / (1.0 + s * mu)).astype(np.float32)
