"""Reference values for the profile models (colour-science style: one test per method)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import quad

from skinpipe.profile.models import (
    burley_profile,
    dipole_profile,
    dipole_total_reflectance,
    fit_error_eq2c,
    gaussian_2d,
    ring_widths_mm,
    sum_of_gaussians,
    total_reflectance_numeric,
)
from skinpipe.profile.reference_data import (
    DEON_2007_SKIN,
    JENSEN_2001,
    PARK_OH_2009_FOREHEAD,
    normalized_weights,
)


def test_gaussian_2d_reference_values() -> None:
    assert gaussian_2d(1.0, 0.0) == pytest.approx(1.0 / (2.0 * np.pi))
    assert gaussian_2d(0.5, 1.0) == pytest.approx(np.exp(-1.0) / np.pi)


@pytest.mark.parametrize("variance", [1e-4, 0.0064, 1.0, 7.41])
def test_gaussian_2d_integrates_to_one(variance: float) -> None:
    total, _ = quad(lambda r: 2 * np.pi * r * gaussian_2d(variance, r), 0, 50 * np.sqrt(variance))
    assert total == pytest.approx(1.0, rel=1e-9)


def test_sum_of_gaussians_shapes_and_total() -> None:
    r = np.linspace(0, 40, 40001)
    f = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r)
    assert f.shape == (r.size, 3)
    np.testing.assert_allclose(total_reflectance_numeric(r, f), DEON_2007_SKIN.weights.sum(0),
                               rtol=1e-5)


def test_deon_weights_sum_to_one() -> None:
    np.testing.assert_allclose(DEON_2007_SKIN.weights.sum(axis=0), [1.0, 1.0, 1.0], atol=1e-12)


def test_park_oh_table_as_printed() -> None:
    sums = PARK_OH_2009_FOREHEAD.weights.sum(axis=0)
    np.testing.assert_allclose(sums, [1.0, 1.0926, 1.0], atol=1e-4)
    np.testing.assert_allclose(normalized_weights(PARK_OH_2009_FOREHEAD).sum(axis=0), 1.0)
    # three variances shared by all channels, nine channel-specific ones
    assert PARK_OH_2009_FOREHEAD.variances_mm2.size == 12


@pytest.mark.parametrize(
    ("material", "expected"),
    [("skin1", (0.44, 0.22, 0.13)), ("skin2", (0.63, 0.44, 0.34)), ("marble", (0.83, 0.79, 0.75))],
)
def test_dipole_total_reflectance_matches_published(material: str, expected: tuple) -> None:
    np.testing.assert_allclose(dipole_total_reflectance(JENSEN_2001[material]), expected,
                               atol=0.011)


@pytest.mark.parametrize("material", ["skin1", "skin2", "marble", "ketchup"])
def test_dipole_profile_integrates_to_closed_form(material: str) -> None:
    coeffs = JENSEN_2001[material]
    closed = dipole_total_reflectance(coeffs)
    for c in range(3):
        def integrand(r: float, c: int = c) -> float:
            return 2 * np.pi * r * dipole_profile(np.array([r]), coeffs)[0, c]
        total, _ = quad(integrand, 0, np.inf, limit=400)
        assert total == pytest.approx(closed[c], rel=1e-4)


def test_burley_integrates_to_albedo_and_is_singular() -> None:
    albedo, mfp = np.array([0.8, 0.5, 0.3]), np.array([1.0, 0.5, 0.25])
    for c in range(3):
        def integrand(r: float, c: int = c) -> float:
            return 2 * np.pi * r * burley_profile(np.array([r]), albedo, mfp)[0, c]
        total, _ = quad(integrand, 0, np.inf, limit=400)
        assert total == pytest.approx(albedo[c], rel=1e-6)
    assert np.all(np.isinf(burley_profile(np.array([0.0]), albedo, mfp)))


def test_ring_widths_cover_the_axis() -> None:
    r = np.array([0.0, 0.1, 0.3, 0.7])
    np.testing.assert_allclose(ring_widths_mm(r), [0.05, 0.15, 0.3, 0.2])
    assert ring_widths_mm(r).sum() == pytest.approx(r[-1] - r[0])


def test_fit_error_eq2c_reference_values() -> None:
    r = np.linspace(0, 2, 50)
    f = np.exp(-r)[:, None] * np.ones((1, 3))
    np.testing.assert_allclose(fit_error_eq2c(r, f, f), 0.0)
    np.testing.assert_allclose(fit_error_eq2c(r, 1.01 * f, f), 0.01, rtol=1e-12)
    assert np.all(np.isinf(fit_error_eq2c(r, f, 0 * f)))


def test_fit_error_ignores_the_entry_point_weight() -> None:
    # r = 0 has zero area weight (eq. 2c): a wrong value there costs nothing.
    r = np.linspace(0, 1, 11)
    f = np.ones((11, 1))
    p = f.copy()
    p[0] = 100.0
    assert fit_error_eq2c(r, p, f)[0] == 0.0


def test_expected_eq2c_error_matches_monte_carlo() -> None:
    """The eq. 2c error that independent noise of known standard deviation gives a
    profile, predicted, against 400 noisy copies measured."""
    from skinpipe.profile.models import expected_error_eq2c, fit_error_eq2c

    r = np.linspace(0.01, 4.0, 160)
    p = sum_of_gaussians(DEON_2007_SKIN.variances_mm2, DEON_2007_SKIN.weights, r)
    s = 0.02 * p + 1e-4 * p.max(axis=0)
    rng = np.random.default_rng(3)
    measured = [fit_error_eq2c(r, p + s * rng.standard_normal(p.shape), p) for _ in range(400)]
    rms = np.sqrt(np.mean(np.square(measured), axis=0))
    np.testing.assert_allclose(expected_error_eq2c(r, p, s), rms, rtol=0.05)


def test_tail_beyond_the_image_follows_its_model() -> None:
    """A profile seen to 4 mm whose widest term leaves the frame: the flux beyond the
    disk from the measured tail, against the analytic one (a sum of Gaussians, whose
    tail is its widest Gaussian: 2 pi int_R^inf w G(v) r dr = w exp(-R^2 / 2v))."""
    from skinpipe.profile.models import disk_radius_mm, extrapolated_tail, ring_areas_mm2

    r = np.arange(0.025, 4.0, 0.025)
    v, w = np.array([0.05, 0.5, 2.5]), np.array([0.3, 0.4, 0.3])
    p = sum_of_gaussians(v, w, r)[:, None]
    tail = extrapolated_tail(r, p, 0.01 * p)
    edge = disk_radius_mm(r)
    true_beyond = float(w[-1] * np.exp(-edge**2 / (2 * v[-1])))
    assert tail.model == ("gaussian",)
    # within 5% of itself (measured 3.2%: the next term still adds 7% at 2.4 mm)
    assert tail.flux_beyond[0] == pytest.approx(true_beyond, rel=0.05)
    disk = float((p[:, 0] * ring_areas_mm2(r)).sum())
    assert disk + tail.flux_beyond[0] == pytest.approx(1.0, abs=2e-3)
    assert disk < 0.99  # without the tail the profile would read 1.2% too high


@pytest.mark.parametrize("material", ["skin1", "skin2"])
def test_dipole_tail_is_extrapolated_with_its_far_field(material: str) -> None:
    """A diffusion dipole with Jensen et al. 2001's measured skin (an independent model
    and data) seen to 4 mm: the share of its light beyond the image is recovered within
    the stated uncertainty, per channel."""
    from skinpipe.profile.models import disk_radius_mm, extrapolated_tail

    coeffs = JENSEN_2001[material]
    r = np.arange(0.025, 4.0, 0.025)
    p = dipole_profile(r, coeffs)
    tail = extrapolated_tail(r, p, 0.01 * p)
    rf = np.linspace(0.0, 400.0, 800001)
    pf = dipole_profile(rf, coeffs)
    total = 2 * np.pi * np.trapezoid(pf * rf[:, None], rf, axis=0)
    inside = rf <= disk_radius_mm(r)
    true_share = 1 - 2 * np.pi * np.trapezoid((pf * rf[:, None])[inside], rf[inside],
                                              axis=0) / total
    assert np.all(np.abs(tail.fraction_beyond - true_share) <= tail.scale_uncertainty
                  + 1e-3), (tail.model, tail.fraction_beyond, true_share)


def test_a_channel_holding_another_channels_longer_tail() -> None:
    """A camera channel is a band of the spectrum, and bands overlap: a green that holds
    3% of a red whose tail reaches much farther (Jensen et al. 2001's skin1 dipoles,
    integrated here to 400 mm) has its far tail set by that red. Seen to 6.4 mm, a
    dipole of its own reads the green's share beyond the image 10% of itself low; the
    own dipole with some of the red's ("dipole+mix") within 3% (measured 0.03%), and the
    stated uncertainty covers it."""
    from skinpipe.profile.models import disk_radius_mm, extrapolated_tail

    coeffs = JENSEN_2001["skin1"]
    r = np.arange(0.02, 6.4, 0.04)
    mix = np.array([[1.0, 0.0, 0.0], [0.03, 0.97, 0.0], [0.0, 0.0, 1.0]])
    p = dipole_profile(r, coeffs) @ mix.T
    rf = np.linspace(0.0, 400.0, 800001)
    pf = (dipole_profile(rf, coeffs) @ mix.T) * rf[:, None]
    inside = rf <= disk_radius_mm(r)
    true_share = 1 - np.trapezoid(pf[inside], rf[inside], axis=0) / np.trapezoid(pf, rf, axis=0)
    tail = extrapolated_tail(r, p, 0.002 * p)
    assert tail.model[1] == "dipole+mix", tail.model
    assert tail.fraction_beyond[1] == pytest.approx(true_share[1], rel=0.03)
    assert np.all(np.abs(tail.fraction_beyond - true_share) <= tail.scale_uncertainty + 1e-4)
