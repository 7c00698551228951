"""The measurement for renderers that are not skinpipe: per-region OpenPBR values.

Each region's profile is inverted to the homogeneous medium that reproduces it
(:mod:`skinpipe.profile.medium`), and the medium is written as OpenPBR 1.1 defines its
subsurface (§"Subsurface" of the specification): ``subsurface_radius`` times
``subsurface_radius_scale`` is the mean free path 1 / mu_t per channel, in scene units;
``subsurface_color`` the multiple-scattering albedo whose van de Hulst inversion (the
formula the specification gives) returns the medium's single-scattering albedo;
``subsurface_scatter_anisotropy`` the medium's Henyey-Greenstein g.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..profile.edge import ring_means_of_gaussians
from ..profile.medium import MediumEstimate, estimate_medium
from ..profile.types import FitResult, MeasuredProfile

RING_MM = 0.025
"""Ring width of the profile a fit without measured samples is inverted on."""
MAX_RINGS = 600
SPECULAR_ROUGHNESS = 0.35
SPECULAR_IOR = 1.4
"""Skin's refractive index (OpenPBR's specular_ior; the preview surface's ior)."""


def region_medium(fit: FitResult, measured: MeasuredProfile | None,
                  albedo: tuple[float, float, float]) -> MediumEstimate:
    """The medium of one region: its measured samples (or, without them, the fit's
    Gaussians as ring means out to five standard deviations of the widest term), made to
    reflect ``albedo``: what skinpipe's render gives the region's pencil (the profile's
    weights sum to 1; the albedo carries the level, as in the render)."""
    if measured is not None and measured.radius_mm.size >= 3:
        radius, values = measured.radius_mm, measured.values
    else:
        reach = 5.0 * math.sqrt(float(np.max(fit.variances_mm2)))
        width = max(RING_MM, reach / MAX_RINGS)
        radius = width * (np.arange(math.ceil(reach / width)) + 0.5)
        values = ring_means_of_gaussians(radius, fit.variances_mm2, fit.weights)
    return estimate_medium(radius, np.clip(values, 0.0, None), np.asarray(albedo, np.float64))


def openpbr_values(medium: MediumEstimate, meters_per_unit: float,
                   base_color: tuple[float, float, float]) -> dict[str, Any]:
    """OpenPBR's inputs for ``medium`` in a stage of ``meters_per_unit``."""
    mfp_units = np.asarray(medium.mean_free_path_mm) / (meters_per_unit * 1000.0)
    radius = float(mfp_units.max())
    return {"base_color": tuple(float(x) for x in base_color), "subsurface_weight": 1.0,
            "subsurface_color": _f32(medium.subsurface_colour),
            "subsurface_radius": radius,
            "subsurface_radius_scale": _f32(mfp_units / radius),
            "subsurface_scatter_anisotropy": float(medium.anisotropy),
            "specular_roughness": SPECULAR_ROUGHNESS, "specular_ior": SPECULAR_IOR}


def face_weighted_medium(media: list[MediumEstimate], faces: NDArray[Any]) -> MediumEstimate:
    """One medium for a whole mesh (renderers that ignore GeomSubset bindings): the
    regions' albedos, mean free paths and anisotropies averaged by their numbers of
    faces."""
    w = np.bincount(np.asarray(faces), minlength=len(media))[:len(media)].astype(np.float64)
    w = w / w.sum() if w.sum() > 0 else np.full(len(media), 1.0 / len(media))

    def mean(name: str) -> NDArray[np.float64]:
        return np.einsum("r,rc->c", w, np.array([getattr(m, name) for m in media]))

    return MediumEstimate(mean("single_scattering_albedo"), mean("mean_free_path_mm"),
                          float(w @ np.array([m.anisotropy for m in media])),
                          mean("total_reflectance"), mean("error_eq2c"), mean("edge_error"),
                          media[0].model)


def _f32(values: Any) -> tuple[float, ...]:
    return tuple(float(np.float32(x)) for x in np.asarray(values, np.float64).reshape(-1))
