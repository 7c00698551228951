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
    trace_slab_from_below,
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


def test_an_almost_absorbing_slab_lets_through_its_single_scattering() -> None:
    """Lit uniformly from below, seen from straight above: the first collisions send up
    a tau e^-tau / (4 pi) per unit irradiance (isotropic; the beam to the collision and
    the way up together cross the slab once), all that leaves at albedo 1e-3."""
    for tau in (0.5, 2.0):
        m = Medium(sigma_s=0.001, sigma_a=0.999)
        want = 0.001 * tau * math.exp(-tau) / (4 * math.pi)
        assert trace_slab_from_below(m, tau, 100_000, seed=9) == pytest.approx(want,
                                                                              rel=0.01)


@pytest.mark.slow  # three Mitsuba renders a thickness
def test_the_slab_from_below_is_mitsubas() -> None:
    """skin1 2 and 5 mm thick, lit from below: Mitsuba 3's volpath (4096 samples a
    pixel, a null boundary, the unscattered beam a delta it does not see) within 1.5%."""
    mi = pytest.importorskip("mitsuba")
    try:
        mi.set_variant("llvm_ad_mono")
    except (AttributeError, ImportError):
        mi.set_variant("scalar_mono")
    transform = mi.ScalarTransform4f
    for thickness in (2.0, 5.0):
        for c in range(3):
            m = medium("skin1", c)
            scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "volpath", "max_depth": -1},
                "sensor": {"type": "orthographic",
                           "to_world": transform.look_at(origin=[0, 0, 10], target=[0, 0, 0],
                                                         up=[0, 1, 0])
                           @ transform.scale([2, 2, 1]),
                           "film": {"type": "hdrfilm", "width": 16, "height": 16,
                                    "rfilter": {"type": "box"}},
                           "sampler": {"type": "independent", "sample_count": 4096}},
                "light": {"type": "directional", "direction": [0, 0, 1], "irradiance": 1.0},
                "slab": {"type": "cube", "bsdf": {"type": "null"},
                         "to_world": transform.translate([0, 0, -thickness / 2])
                         @ transform.scale([200, 200, thickness / 2]),
                         "interior": {"type": "homogeneous", "albedo": m.albedo,
                                      "sigma_t": m.sigma_t, "phase": {"type": "isotropic"}}}})
            got = float(np.array(mi.render(scene)).mean())
            want = trace_slab_from_below(m, thickness, 200_000, seed=21 + c)
            assert got == pytest.approx(want, rel=0.015), (thickness, c)


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
