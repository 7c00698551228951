"""Lighting: Fresnel, Beckmann and Torrance-Sparrow references; light sampling against
closed-form irradiance."""

from __future__ import annotations

import math

import numpy as np

from pipeline.lighting import (
    beckmann_ndf,
    fresnel_schlick,
    irradiance_texture,
    specular_albedo,
)
from pipeline.raytrace import RayScene, morton_order
from pipeline.scene import Light


def test_fresnel_schlick_reference_values() -> None:
    # F0 = ((1.4 - 1) / (1.4 + 1))^2 = 0.02778 for skin (eta 1.4); 1 at grazing
    np.testing.assert_allclose(fresnel_schlick(1.0), 0.0277778, rtol=1e-5)
    np.testing.assert_allclose(fresnel_schlick(0.0), 1.0)
    assert np.all(np.isfinite(fresnel_schlick(np.array([np.nan, -2.0, 5.0]))[1:]))


def test_beckmann_is_normalised_over_the_hemisphere() -> None:
    theta = (np.arange(4000) + 0.5) / 4000 * (math.pi / 2)
    d_theta = math.pi / 2 / 4000
    for m in (0.2, 0.35, 0.6):
        total = (beckmann_ndf(np.cos(theta), m) * np.cos(theta) * np.sin(theta)).sum() \
            * d_theta * 2 * math.pi
        assert abs(total - 1.0) < 2e-3, m


def test_specular_albedo_is_small_and_rises_at_grazing() -> None:
    rho = specular_albedo(np.array([1.0, 0.5, 0.1]))
    assert 0.0 < rho[0] < rho[1] < rho[2] < 0.25  # never more than rho_s
    assert specular_albedo(1.0, rho_s=0.0) == 0.0


def _floor() -> RayScene:
    pts = np.array([[-1e3, -1e3, -1.0], [1e3, -1e3, -1.0], [0.0, 1e3, -1.0]])
    return RayScene([(pts, np.array([[0, 1, 2]]))])


def test_sphere_light_irradiance_matches_the_closed_form() -> None:
    # a sphere of radius R at distance D straight above: E = L pi (R / D)^2
    matrix = np.eye(4)
    matrix[3, :3] = [0.0, 0.0, 10.0]
    light = Light("/S", "sphere", np.ones(3), matrix, radius=2.0)
    pos = np.zeros((1, 3))
    nrm = np.array([[0.0, 0.0, 1.0]])
    res = irradiance_texture(pos, nrm, [light], _floor(), samples=256, rho_s=0.0)
    np.testing.assert_allclose(res.entering[0], math.pi * 0.04, rtol=1e-2)


def test_dome_light_white_furnace() -> None:
    light = Light("/D", "dome", np.full(3, 0.5), np.eye(4))
    res = irradiance_texture(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), [light], _floor(),
                             samples=64, rho_s=0.0)
    np.testing.assert_allclose(res.entering[0], 0.5 * math.pi, rtol=1e-5)


def test_morton_order_is_a_permutation_that_groups_neighbours() -> None:
    rng = np.random.default_rng(0)
    pts = rng.random((1000, 3))
    order = morton_order(pts)
    assert sorted(order.tolist()) == list(range(1000))
    step = np.linalg.norm(np.diff(pts[order], axis=0), axis=1).mean()
    assert step < 0.5 * np.linalg.norm(np.diff(pts, axis=0), axis=1).mean()
