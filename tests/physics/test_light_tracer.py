"""The light tracer (tests/physics/light_tracer.py) against closed forms it does not use,
and the stored pencil profiles (tests/fixtures/physics/) against a cheap new trace."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from .light_tracer import (
    LIT_ANGLES_DEG,
    Medium,
    fresnel,
    medium,
    single_scattering_index_matched,
    trace,
)

FIXTURES = Path(__file__).parents[1] / "fixtures" / "physics"


def _chandrasekhar_h(albedo: float, mu: np.ndarray) -> np.ndarray:
    """H(mu) of isotropic scattering, by iterating 1/H(mu) = sqrt(1 - a) + (a/2) int_0^1
    mu' H(mu') / (mu + mu') dmu' (Chandrasekhar 1960, eq. V.41) on Gauss-Legendre nodes."""
    x, w = np.polynomial.legendre.leggauss(64)
    nodes, weights = 0.5 * (x + 1), 0.5 * w
    h = np.ones_like(nodes)
    for _ in range(500):
        h = 1 / (math.sqrt(1 - albedo) + albedo / 2 * (
            nodes[:, None] * h[:, None] * weights[:, None] / (nodes[None, :] + nodes[:, None])
        ).sum(axis=0))
    return 1 / (math.sqrt(1 - albedo) + albedo / 2 * (
        nodes[:, None] * h[:, None] * weights[:, None] / (mu[None, :] + nodes[:, None])
    ).sum(axis=0))


def test_fresnel_is_the_textbook_reflectance() -> None:
    assert fresnel(np.array([1.0]), 1.0, 1.4)[0] == pytest.approx(((1.4 - 1) / 2.4) ** 2)
    assert fresnel(np.array([0.2]), 1.4, 1.0)[0] == 1.0  # beyond the critical angle
    assert fresnel(np.array([0.5]), 1.0, 1.0)[0] == pytest.approx(0.0, abs=1e-12)


def test_an_almost_absorbing_medium_sends_up_its_single_scattering() -> None:
    """Albedo 1e-4: what leaves is single scattering, a p(-1) / 2 (closed form), within
    the trace's noise (0.2% at 200,000 photons) and multiple scattering's 0.04%."""
    m = Medium(sigma_s=0.001, sigma_a=10.0, g=0.5)
    tally = trace(m, 200_000, np.array([1.0]), seed=3)
    assert tally.total == pytest.approx(single_scattering_index_matched(m), rel=0.01)


def test_an_isotropic_half_space_reflects_as_chandrasekhar_says() -> None:
    """Index-matched, isotropic, albedo 0.9, a normal pencil: the up-radiance per unit
    incident power, summed over the surface, is the reflection function
    a H(1)^2 / (8 pi) (Chandrasekhar 1960, eq. IV.14 at mu = mu0 = 1)."""
    albedo = 0.9
    m = Medium(sigma_s=albedo, sigma_a=1 - albedo)
    want = albedo * _chandrasekhar_h(albedo, np.array([1.0]))[0] ** 2 / (8 * math.pi)
    tally = trace(m, 200_000, np.array([50.0]), seed=5)
    assert tally.total == pytest.approx(want, rel=0.01)


@pytest.mark.parametrize("channel", [0, 2])
def test_the_stored_skin1_profile_is_what_a_new_trace_gives(channel: int) -> None:
    """A cheap slice: 40,000 photons of skin1 against the stored 500,000, the light within
    0.025 (the entry spike), 0.5, 2 and 8 mm, within the new trace's noise."""
    rows = np.loadtxt(FIXTURES / "skin1.csv", delimiter=",", skiprows=1)
    r, stored = rows[:, 0], rows[:, 1 + channel]
    edges = r + 0.0125
    tally = trace(medium("skin1", channel), 40_000, edges, seed=11)
    inner = np.concatenate([[0.0], edges[:-1]])
    area = math.pi * (edges**2 - inner**2)
    new = np.cumsum(tally.radiance() * area)
    new /= new[-1]
    old = np.cumsum(stored * area)
    for radius in (0.025, 0.5, 2.0, 8.0):
        i = int(np.searchsorted(edges, radius - 1e-9))
        assert new[i] == pytest.approx(old[i], abs=0.01), radius
    totals = json.loads((FIXTURES / "totals.json").read_text())["skin1"]["channels"]
    assert tally.total == pytest.approx(totals[channel]["up_radiance_total"], rel=0.03)
    assert set(totals[channel]["lit_up_radiance"]) == {str(a) for a in LIT_ANGLES_DEG}
