"""The specular lobe (Torrance & Sparrow 1967 with Beckmann's distribution and Schlick's
Fresnel, the paper's section 4: roughness 0.35, rho_s 0.25): the reflection a viewer
sees. What crosses the surface into the skin is :mod:`.boundary`'s."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..options import DEFAULT_RHO_S, DEFAULT_ROUGHNESS
from .boundary import SKIN_IOR


def fresnel_schlick(cos_theta: NDArray[Any], ior: float = SKIN_IOR) -> NDArray[np.float64]:
    """Schlick's approximation of the dielectric Fresnel reflectance (Schlick 1994)."""
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2
    c = np.clip(np.asarray(cos_theta, dtype=np.float64), 0.0, 1.0)
    return f0 + (1.0 - f0) * (1.0 - c) ** 5


def beckmann_ndf(cos_h: NDArray[Any], roughness: float) -> NDArray[np.float64]:
    """Beckmann microfacet distribution D(h), normalised so that int D cos_h dw = 1."""
    c = np.clip(np.asarray(cos_h, dtype=np.float64), 1e-6, 1.0)
    m2 = roughness * roughness
    tan2 = (1.0 - c * c) / (c * c)
    return np.exp(-tan2 / m2) / (math.pi * m2 * c ** 4)


def torrance_sparrow(n_dot_l: NDArray[Any], n_dot_v: NDArray[Any], n_dot_h: NDArray[Any],
                     v_dot_h: NDArray[Any], roughness: float = DEFAULT_ROUGHNESS,
                     rho_s: float = DEFAULT_RHO_S) -> NDArray[np.float64]:
    """Torrance-Sparrow BRDF rho_s D F G / (4 (n.l)(n.v)) (Torrance & Sparrow 1967; Cook &
    Torrance 1982's shadowing term G), zero below the horizon."""
    nl = np.asarray(n_dot_l, dtype=np.float64)
    nv = np.asarray(n_dot_v, dtype=np.float64)
    nh = np.asarray(n_dot_h, dtype=np.float64)
    vh = np.clip(np.asarray(v_dot_h, dtype=np.float64), 1e-6, 1.0)
    g = np.minimum(1.0, np.minimum(2 * nh * nv / vh, 2 * nh * nl / vh))
    ok = (nl > 0) & (nv > 0)
    denom = 4.0 * np.where(ok, nl * nv, 1.0)
    f = rho_s * beckmann_ndf(nh, roughness) * fresnel_schlick(vh) * g / denom
    return np.where(ok, f, 0.0)
