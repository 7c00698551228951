"""The specular lobe (Torrance & Sparrow 1967 with Beckmann's distribution and Schlick's
Fresnel, the paper's section 4: roughness 0.35, rho_s 0.25) and its directional albedo
rho_dt, the share of light that does not enter the skin."""

from __future__ import annotations

import math
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..cache import kept, source_of
from ..options import DEFAULT_RHO_S, DEFAULT_ROUGHNESS

SKIN_IOR = 1.4


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


def rho_dt_quadrature(roughness: float, rho_s: float, n: int = 64) -> NDArray[np.float64]:
    """rho_dt(cos theta) on n cosines from 0 to 1 by midpoint quadrature over the
    hemisphere of outgoing directions (polar 256 x azimuth 128) of
    :func:`torrance_sparrow` times cos theta_o: the lobe's directional albedo (d'Eon &
    Luebke 2007, GPU Gems 3 ch. 14, which tabulates it the same way)."""
    cos_in = np.linspace(0.0, 1.0, n)
    theta = (np.arange(256) + 0.5) / 256 * (math.pi / 2)
    phi = (np.arange(128) + 0.5) / 128 * math.pi  # symmetric in phi: integrate half, x2
    tt, pp = np.meshgrid(theta, phi, indexing="ij")
    out_dir = np.stack([np.sin(tt) * np.cos(pp), np.sin(tt) * np.sin(pp), np.cos(tt)], -1)
    d_omega = np.sin(tt) * (math.pi / 2 / 256) * (math.pi / 128) * 2
    table = np.zeros(n)
    for i, c in enumerate(cos_in):
        if c <= 0:
            continue
        light = np.array([math.sqrt(max(0.0, 1 - c * c)), 0.0, c])
        h = out_dir + light
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        f = torrance_sparrow(c, out_dir[..., 2], h[..., 2], (out_dir * h).sum(-1),
                             roughness, rho_s)
        table[i] = float((f * out_dir[..., 2] * d_omega).sum())
    table[0] = table[1]
    return table


@lru_cache(maxsize=8)
def _rho_dt_table(roughness: float, rho_s: float, n: int = 64) -> NDArray[np.float64]:
    """:func:`rho_dt_quadrature`, kept in skinpipe's cache folder by numpy's version, the
    source of the functions that make it and the arguments: the quadrature was 0.2 s of
    the main thread before the rays in every render. Read-only: every caller shares it."""
    def read(doc: dict[str, Any]) -> NDArray[np.float64]:
        table = np.asarray(doc["table"], np.float64)
        if table.shape != (n,) or not np.all(np.isfinite(table) & (table >= 0)):
            raise ValueError("kept rho_dt table of another size or not finite")
        return table

    def make() -> tuple[NDArray[np.float64], dict[str, Any]]:
        table = rho_dt_quadrature(roughness, rho_s, n)
        return table, {"table": table.tolist()}  # repr: each float64 read back exactly

    source = source_of(rho_dt_quadrature, torrance_sparrow, beckmann_ndf, fresnel_schlick)
    table = kept("specular-albedo", "rho-dt", [np.__version__, source, roughness, rho_s, n],
                 read, make)
    table.setflags(write=False)
    return table


def specular_albedo(cos_theta: NDArray[Any], roughness: float = DEFAULT_ROUGHNESS,
                    rho_s: float = DEFAULT_RHO_S) -> NDArray[np.float64]:
    """rho_dt: the fraction of light arriving at cos_theta that the specular lobe
    reflects (so 1 - rho_dt enters the skin); linear in the table, in the precision of
    ``cos_theta`` (float32 stays float32: it runs per shadow-ray sample)."""
    c = np.asarray(cos_theta)
    dtype = np.dtype(np.float32 if c.dtype == np.float32 else np.float64)
    table = _rho_dt_table(float(roughness), float(rho_s)).astype(dtype)
    x = np.clip(c.astype(dtype, copy=False), 0, 1) * dtype.type(table.size - 1)
    i = np.minimum(x.astype(np.int32), table.size - 2)
    f = x - i.astype(dtype)
    return table[i] * (1 - f) + table[i + 1] * f
