"""The angular law of a half-space (skinpipe/render/light/reflection_law.py) against the
independent light tracer's lit levels (tests/physics/light_tracer.py, stored in
tests/fixtures/physics/totals.json: the up-radiance under uniform light at 0-75 degrees)
and against Chandrasekhar's law of diffuse reflection, which it must equal at g = 0."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from skinpipe.profile.medium import chandrasekhar_h
from skinpipe.render.light.boundary import SkinBoundary, transmission
from skinpipe.render.light.reflection_law import ReflectionLaw, angular_correction
from skinpipe.render.scene import Light

PHYSICS = Path(__file__).parents[2] / "fixtures" / "physics"
ANGLES = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)


def _traced(name: str) -> tuple[ReflectionLaw, np.ndarray]:
    """The law of a traced medium's true albedo and g, and its lit levels (angle, RGB)
    relative to normal incidence, per unit irradiance of the surface."""
    doc = json.loads((PHYSICS / "totals.json").read_text())[name]
    sigma_s, sigma_a, g, eta = doc["medium"]
    albedo = np.asarray(sigma_s) / (np.asarray(sigma_s) + np.asarray(sigma_a))
    lit = np.array([[c["lit_up_radiance"][str(a)] for c in doc["channels"]] for a in ANGLES])
    return ReflectionLaw(albedo[None], np.array([g]), eta), lit / lit[0]


@pytest.mark.parametrize(("name", "within"), [("skin1", 0.005), ("skin1_eta1.4", 0.02),
                                              ("marble", 0.035)])
def test_the_law_follows_the_light_tracer_from_0_to_75_degrees(name: str,
                                                                within: float) -> None:
    """Seen from straight above: index-matched skin1 (a fifth to a half of its light
    singly scattered) exactly; behind a boundary (index 1.4, 1.5) within 2-3.5%."""
    law, truth = _traced(name)
    cos = np.cos(np.radians(ANGLES))
    got = law.relative(cos, np.ones_like(cos), cos) * transmission(cos, law.eta)[:, None]
    assert np.all(np.abs(got / truth - 1) < within), np.round(got / truth, 3).tolist()


def test_isotropic_law_is_chandrasekhars_and_reciprocal() -> None:
    """At g = 0, index-matched: alpha H(mu_i) H(mu_o) / (4 pi (mu_i + mu_o)) relative to
    its normal value, the same with light and eye swapped."""
    albedo = np.array([0.99, 0.8, 0.3])
    law = ReflectionLaw(albedo[None], np.zeros(1), 1.0)
    rng = np.random.default_rng(3)
    mu_i, mu_o = rng.uniform(0.05, 1, 50), rng.uniform(0.05, 1, 50)
    phi_az = rng.uniform(0, 2 * math.pi, 50)
    l_dot_v = mu_i * mu_o + np.sqrt(1 - mu_i**2) * np.sqrt(1 - mu_o**2) * np.cos(phi_az)
    got = law.relative(mu_i, mu_o, l_dot_v)
    for c, a in enumerate(albedo):
        h1 = float(chandrasekhar_h(a, 1.0))
        want = chandrasekhar_h(a, mu_i) * chandrasekhar_h(a, mu_o) / (mu_i + mu_o) \
            / (h1 * h1 / 2)
        np.testing.assert_allclose(got[:, c], want, rtol=1e-4)
    np.testing.assert_allclose(law.relative(mu_o, mu_i, l_dot_v), got, rtol=1e-5)


def test_single_scattering_follows_the_phase_function() -> None:
    """Forward scattering (g = 0.8) sends light arriving at a grazing angle on, away from
    the light: seen from the light's side it is darker than seen from the far side; at
    g = 0 the two agree."""
    mu = np.array([0.5, 0.5])
    l_dot_v = np.array([1.0, 2 * 0.25 - 1])  # eye at the light; eye mirrored across n
    forward = ReflectionLaw(np.full((1, 3), 0.9), np.array([0.8])).relative(mu, mu, l_dot_v)
    assert np.all(forward[0] < forward[1])
    iso = ReflectionLaw(np.full((1, 3), 0.9), np.zeros(1)).relative(mu, mu, l_dot_v)
    np.testing.assert_allclose(iso[0], iso[1], rtol=1e-6)


def test_regions_blend_by_weight_and_normal_light_needs_no_correction() -> None:
    law = ReflectionLaw(np.array([[0.99] * 3, [0.5] * 3]), np.array([0.0, 0.7]))
    cos = np.array([0.3, 0.3])
    one = law.relative(cos, np.ones(2), cos, np.array([[1.0, 0.0], [0.0, 1.0]]))
    mixed = law.relative(cos[:1], np.ones(1), cos[:1], np.array([[0.25, 0.75]]))
    np.testing.assert_allclose(mixed[0], 0.25 * one[0] + 0.75 * one[1], rtol=1e-6)
    np.testing.assert_allclose(law.relative(np.ones(1), np.ones(1), np.ones(1)), 1.0,
                               rtol=1e-6)
    sun = Light(path="/Sun", kind="distant", radiance=np.ones(3), matrix=np.eye(4))
    pos, n = np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1))
    delta = angular_correction(law, SkinBoundary(1.0), [sun], pos, n, n,
                               {"/Sun": np.ones(2, np.float32)}, np.ones((2, 3), np.float32),
                               np.array([[1.0, 0.0], [0.0, 1.0]]))
    np.testing.assert_allclose(delta, 0.0, atol=1e-6)
