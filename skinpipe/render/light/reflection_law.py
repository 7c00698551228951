"""How the light a half-space of skin sends back depends on the light's and the eye's
angles: the law the diffusion's Lambertian exit leaves out.

A measured profile and its albedo are what a camera straight above saw under light from
straight above. The diffusion spreads that light over the surface and lets it leave as a
Lambertian source, weighted on entry by the boundary's transmission and the depth factor
D (:mod:`.boundary`). A homogeneous half-space of single-scattering albedo alpha and
Henyey-Greenstein anisotropy g, lit by irradiance E arriving at cosine mu_i, sends towards
mu_o the radiance E f with

    f = alpha p_g(cos Theta) / (mu_i + mu_o)
        + alpha' (H(mu_i) H(mu_o) - 1) / (4 pi (mu_i + mu_o)).

The first term is single scattering (Hanrahan & Krueger 1993, §4: the first-order
solution, Theta the angle between the light's travel and the eye's direction). The
second is the multiply scattered rest of Chandrasekhar's law of diffuse reflection for
isotropic scattering, alpha H(mu_i) H(mu_o) / (4 pi (mu_i + mu_o)) (Chandrasekhar 1960,
ch. IV; the law whose normal value gives medium.py's pencil reflectance), less its own
first order, at the similarity relation's reduced albedo alpha' = alpha (1 - g) /
(1 - alpha g) with H = H(alpha'). At g = 0 the sum is Chandrasekhar's law: exact. Behind a
boundary of index eta the cosines and Theta are the refracted directions' (Snell), and
the Fresnel transmissions stay the boundary's.

The render uses the law for index-matched skin (``--ior 1``), relative to normal
incidence and exit, phi = f / f(1, 1, -1), as the measured albedo is the normal one: per
light, at the camera's hits, the diffusion's local level is moved from D(mu_i) to phi.
docs/render.md gives its figures against the light tracer and what it leaves out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ...profile.medium import chandrasekhar_h, henyey_greenstein, similarity_relation
from ..scene import Light
from .boundary import SkinBoundary, refracted_cos, transmission
from .irradiance import incidence_cos
from .samples import light_direction

MU_NODES = 257
"""Cosines at which H is tabulated for the lookups (linear: within 1e-5 of H)."""

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ReflectionLaw:
    """The law of a skin mesh's media: per region (R) and channel (3) ``albedo`` (the
    single-scattering albedo), per region ``anisotropy`` (g), behind index ``eta``."""

    albedo: FloatArray
    anisotropy: FloatArray
    eta: float = 1.0
    h_tables: FloatArray = field(init=False, repr=False, compare=False)
    """H(alpha'; mu) at :data:`MU_NODES` cosines from 0 to 1, (R, 3, MU_NODES)."""

    def __post_init__(self) -> None:
        a = np.clip(np.asarray(self.albedo, np.float64).reshape(-1, 3), 0.0, 1.0)
        g = np.asarray(self.anisotropy, np.float64).reshape(-1)
        if g.size != a.shape[0]:
            raise ValueError(f"{a.shape[0]} regions' albedos, {g.size} anisotropies")
        object.__setattr__(self, "albedo", a)
        object.__setattr__(self, "anisotropy", g)
        mu = np.linspace(0.0, 1.0, MU_NODES)
        object.__setattr__(self, "h_tables", np.array(
            [[chandrasekhar_h(float(a), mu) for a in row] for row in self.reduced_albedo]))

    @property
    def reduced_albedo(self) -> FloatArray:
        """alpha' (:func:`~skinpipe.profile.medium.similarity_relation`), (R, 3)."""
        return similarity_relation(self.albedo, self.anisotropy[:, None])[0]

    def radiance(self, mu_i: FloatArray, mu_o: FloatArray, cos_theta: FloatArray,
                 region: int) -> FloatArray:
        """f (N, 3) of region ``region`` per unit irradiance at refracted cosines ``mu_i``,
        ``mu_o`` (N,) and scattering cosine ``cos_theta`` (N,)."""
        h = self.h_tables[region]
        nodes = np.linspace(0.0, 1.0, MU_NODES)
        mi, mo = mu_i[:, None], mu_o[:, None]
        hh = np.stack([np.interp(mu_i, nodes, h[c]) * np.interp(mu_o, nodes, h[c])
                       for c in range(3)], axis=1)
        single = self.albedo[region] * henyey_greenstein(
            cos_theta, self.anisotropy[region])[:, None]
        multiple = self.reduced_albedo[region] * (hh - 1.0) / (4.0 * math.pi)
        return (single + multiple) / np.maximum(mi + mo, 1e-6)

    def relative(self, n_dot_l: ArrayLike, n_dot_v: ArrayLike, l_dot_v: ArrayLike,
                 weights: ArrayLike | None = None) -> NDArray[np.float32]:
        """phi (N, 3): the radiance towards ``v`` under light from ``l`` relative to
        normal incidence and exit, for cosines outside the skin (n.l, n.v, l.v), the
        regions' laws blended by ``weights`` (N, R) (None: equally)."""
        nl = np.clip(np.asarray(n_dot_l, np.float64), 0.0, 1.0)
        nv = np.clip(np.asarray(n_dot_v, np.float64), 0.0, 1.0)
        lv = np.asarray(l_dot_v, np.float64)
        mu_i, mu_o = refracted_cos(nl, self.eta), refracted_cos(nv, self.eta)
        # the light travels along -l refracted, the eye's ray leaves along v refracted:
        # their tangential parts shrink by eta, their normal parts are the cosines
        cos_theta = -(lv - nl * nv) / (self.eta * self.eta) - mu_i * mu_o
        one = np.ones(1)
        n_regions = self.albedo.shape[0]
        w = np.full((nl.size, n_regions), 1.0 / n_regions) if weights is None else \
            np.asarray(weights, np.float64).reshape(nl.size, n_regions)
        # regions of one medium (the sample face's five) are one law: their weights add
        media = np.column_stack([self.albedo, self.anisotropy])
        _, first, group = np.unique(media, axis=0, return_index=True, return_inverse=True)
        out = np.zeros((nl.size, 3))
        for k, r in enumerate(first):
            wk = w[:, group.reshape(-1) == k].sum(axis=1)
            at = wk > 0
            normal = self.radiance(one, one, -one, int(r))[0]
            out[at] += wk[at, None] * self.radiance(
                mu_i[at], mu_o[at], cos_theta[at], int(r)) / normal
        return out.astype(np.float32)


def angular_correction(law: ReflectionLaw, boundary: SkinBoundary, lights: list[Light],
                       pos: FloatArray, n: FloatArray, view: FloatArray,
                       visibility: dict[str, NDArray[np.float32]],
                       albedo: NDArray[np.float32], weights: FloatArray | None
                       ) -> NDArray[np.float32]:
    """What the law adds to the diffused radiance at hits ``pos`` (normals ``n``, towards
    the camera ``view``), before the exit's transmission: per light but domes (lit by
    its ``visibility`` there), E cos_i T(theta_i) albedo / pi (phi - D(mu_i)), the local
    level of the diffusion (:mod:`.boundary`'s entry) moved to the law's. Domes keep the
    diffusion's level: their light comes from every angle, where phi averages out."""
    out = np.zeros((pos.shape[0], 3))
    n_dot_v = np.einsum("ij,ij->i", n, view)
    for light in lights:
        if light.kind == "dome" or light.path not in visibility:
            continue
        l_dir, e_perp = light_direction(light, pos)
        n_dot_l = np.clip(np.einsum("ij,ij->i", n, l_dir), 0.0, 1.0)
        lit = n_dot_l * visibility[light.path]
        if not np.any(lit > 0):
            continue
        phi = law.relative(n_dot_l, n_dot_v, np.einsum("ij,ij->i", l_dir, view), weights)
        depth = boundary.depth_factor(incidence_cos(light, pos, n))
        enters = transmission(n_dot_l, boundary.eta)
        out += (lit * enters)[:, None] * e_perp * (phi - depth)
    return (out * albedo / math.pi).astype(np.float32)
