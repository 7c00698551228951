"""Reference profiles sampled the way the paper's camera samples them."""

from __future__ import annotations

import numpy as np

from skinpipe.profile.models import dipole_profile, dipole_total_reflectance, sum_of_gaussians
from skinpipe.profile.reference_data import DEON_2007_SKIN, JENSEN_2001
from skinpipe.profile.types import MeasuredProfile

# About 0.02 mm per pixel out to 4 mm, as in the seed paper's captures.
RADIUS_MM = np.linspace(0.0, 4.0, 200)


def deon_profile(radius_mm: np.ndarray = RADIUS_MM) -> MeasuredProfile:
    values = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, radius_mm)
    return MeasuredProfile(radius_mm, values, name="deon")


def dipole_normalised(material: str, radius_mm: np.ndarray = RADIUS_MM) -> MeasuredProfile:
    coeffs = JENSEN_2001[material]
    values = dipole_profile(radius_mm, coeffs) / dipole_total_reflectance(coeffs)
    return MeasuredProfile(radius_mm, values, name=f"dipole_{material}")
