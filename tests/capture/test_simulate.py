"""The simulator's measured-profile truth (``kind="rings"``) and ``simulate --profile``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from skinpipe.capture.simulate import RegionTruth, read_truth, ring_truth
from skinpipe.cli import main
from skinpipe.errors import InputError

SKIN1 = Path(__file__).parents[1] / "fixtures" / "physics" / "skin1.csv"


def _spike_and_tail() -> RegionTruth:
    r = np.arange(0.0125, 8.0, 0.025)
    mfp = np.array([1.5, 0.8, 0.4])
    values = np.exp(-r[:, None] / mfp) / (2 * np.pi * mfp**2)
    values[0] += 50.0  # a spike in the central ring
    return RegionTruth("x", "rings", ring_radius_mm=tuple(r),
                       ring_values=tuple(map(tuple, values)))


@pytest.mark.parametrize("footprint_mm", [0.0, 0.03, 0.2])
def test_rings_keep_their_light_through_the_footprint(footprint_mm: float) -> None:
    """The observed profile integrates to the rings' light (their areas times values)
    whatever the footprint: its convolution with each ring is exact."""
    from dataclasses import replace

    truth = replace(_spike_and_tail(), footprint_sigma_mm=footprint_mm)
    r = np.linspace(0.0, 12.0, 12001)  # 1 um: the footprint is 30 um or more
    light = np.trapezoid(truth.observed_profile(r) * 2 * np.pi * r[:, None], r, axis=0)
    assert np.allclose(light, truth.albedo_rec709(), rtol=2e-3 if footprint_mm else 2e-2)


def test_a_blurred_ring_matches_brute_force() -> None:
    from dataclasses import replace

    truth = replace(_spike_and_tail(), footprint_sigma_mm=0.05)
    rng = np.random.default_rng(1)
    at = np.array([0.0, 0.04, 0.3])
    points = rng.normal(0.0, 0.05, size=(400_000, 2))
    brute = [truth.scattering_profile(np.hypot(points[:, 0] + x, points[:, 1])).mean(axis=0)
             for x in at]
    assert np.allclose(truth.observed_profile(at), brute, rtol=0.02)


def test_a_ring_profile_must_be_whole() -> None:
    with pytest.raises(InputError, match="two or more"):
        RegionTruth("x", "rings", ring_radius_mm=(0.1,), ring_values=((1, 1, 1),))
    with pytest.raises(InputError, match="rise"):
        RegionTruth("x", "rings", ring_radius_mm=(0.2, 0.1), ring_values=((1, 1, 1),) * 2)


def test_simulate_a_measured_profile(tmp_path: Path) -> None:
    out = tmp_path / "caps"
    assert main(["simulate", "--profile", str(SKIN1), "--size-px", "64",
                 "--camera-colorspace", "lin_ap1_scene", "-o", str(out)]) == 0
    doc = json.loads((out / "capture.json").read_text())
    assert list(doc["regions"]) == ["skin1"]
    truth = read_truth(out / "truth.json")["skin1"]
    assert truth.kind == "rings"
    assert truth.footprint_sigma_mm == 0.03  # the capture's (the realistic preset's)
    assert ring_truth(SKIN1).footprint_sigma_mm == 0.0
    assert np.allclose(truth.ring_values[0], np.loadtxt(SKIN1, delimiter=",", skiprows=1)[0, 1:])
