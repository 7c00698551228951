"""The skin boundary's Fresnel transmission and dipole depth factor against closed forms
(Fresnel's equations at normal, Brewster and grazing incidence; the dipole's limits)."""

from __future__ import annotations

import numpy as np
import pytest

from skinpipe.errors import InputError
from skinpipe.render.light.boundary import (
    SkinBoundary,
    fresnel_dielectric,
    reduced_albedo,
    refracted_cos,
    total_reflectance,
    transmission,
    transmission_lookup,
)


def test_fresnel_at_normal_incidence_is_the_squared_index_ratio() -> None:
    assert fresnel_dielectric(1.0, 1.4) == pytest.approx(((1.4 - 1) / (1.4 + 1)) ** 2)


def test_fresnel_at_brewsters_angle_has_no_p_polarised_reflection() -> None:
    # at Brewster's angle r_p = 0, so F = r_s^2 / 2 with r_s = cos(2 theta_B)... i.e.
    # F = ((eta^2 - 1) / (eta^2 + 1))^2 / 2
    eta = 1.4
    cos_b = np.cos(np.arctan(eta))
    assert fresnel_dielectric(cos_b, eta) == pytest.approx(((eta**2 - 1) / (eta**2 + 1)) ** 2 / 2)


def test_fresnel_reaches_one_at_grazing_light() -> None:
    assert fresnel_dielectric(0.0, 1.4) == pytest.approx(1.0)


def test_transmission_is_one_at_normal_incidence_and_none_below_the_horizon() -> None:
    t = transmission([1.0, 0.5, -0.2], 1.4)
    assert t[0] == pytest.approx(1.0)
    assert 0.0 < t[1] < 1.0
    assert t[2] == 0.0


def test_the_kernel_table_follows_the_exact_transmission() -> None:
    cos = np.cos(np.radians(np.linspace(0, 88, 200)))
    np.testing.assert_allclose(transmission_lookup(cos, 1.4), transmission(cos, 1.4), atol=2e-4)


def test_snell_bends_grazing_light_to_the_critical_angle() -> None:
    assert refracted_cos(0.0, 1.4) == pytest.approx(np.cos(np.arcsin(1 / 1.4)))


def test_reduced_albedo_inverts_the_dipole_reflectance() -> None:
    alpha = np.array([0.3, 0.8, 0.99, 0.9999])
    np.testing.assert_allclose(reduced_albedo(total_reflectance(alpha, 1.4), 1.4), alpha,
                               rtol=1e-4)


def test_a_lossless_medium_reflects_everything_and_a_black_one_nothing() -> None:
    np.testing.assert_allclose(total_reflectance([1.0, 0.0], 1.4), [1.0, 0.0], atol=1e-12)


def test_depth_factor_is_one_at_normal_incidence_and_grows_towards_grazing() -> None:
    b = SkinBoundary.from_albedo([0.5, 0.3, 0.2], 1.4)
    d = b.depth_factor(np.array([1.0, 0.5, 0.1]))
    np.testing.assert_allclose(d[0], 1.0, rtol=1e-6)
    assert np.all(d[1] > d[0]) and np.all(d[2] > d[1])
    # a low albedo (large s) gains most from shallow light
    assert d[2, 2] > d[2, 0]


def test_an_index_outside_one_to_three_is_refused() -> None:
    with pytest.raises(InputError, match="refractive index"):
        SkinBoundary(eta=0.5)
