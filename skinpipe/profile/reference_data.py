"""Published numbers used as physically grounded inputs and as test references.

Units: variances in mm^2, coefficients in mm^-1. Each table names its source.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class GaussianTable:
    """A sum-of-Gaussians profile: ``variances_mm2`` (k,) and ``weights`` (k, 3) in RGB."""

    name: str
    variances_mm2: NDArray[np.float64]
    weights: NDArray[np.float64]
    source: str


DEON_2007_SKIN = GaussianTable(
    name="deon2007_skin",
    variances_mm2=np.array([0.0064, 0.0484, 0.187, 0.567, 1.99, 7.41]),
    weights=np.array(
        [
            [0.233, 0.455, 0.649],
            [0.100, 0.336, 0.344],
            [0.118, 0.198, 0.0],
            [0.113, 0.007, 0.007],
            [0.358, 0.004, 0.0],
            [0.078, 0.0, 0.0],
        ]
    ),
    source=(
        "d'Eon, Luebke, Enderton, 'Efficient Rendering of Human Skin', EGSR 2007 "
        "(GPU Gems 3 ch. 14): six Gaussians fitted to a three-layer multipole skin model"
    ),
)
"""d'Eon et al.'s skin fit; each channel's weights sum to 1 (albedo carries the tint)."""


def _park_oh_forehead() -> GaussianTable:
    # Figure 5 of the seed paper prints per-channel variances; the last three are shared.
    # We lay the table out as one term per distinct (channel, variance) pair, with zero
    # weight in the channels that do not use it, which is how our term lists work.
    per_channel_v = {
        0: [0.0075, 0.0280, 0.0610, 0.1200, 1.8000, 7.4100],
        1: [0.0100, 0.0150, 0.0310, 0.1200, 1.8000, 7.4100],
        2: [0.0125, 0.0290, 0.0680, 0.1200, 1.8000, 7.4100],
    }
    per_channel_w = {
        0: [0.2717, 0.1025, 0.1001, 0.1256, 0.3300, 0.0701],
        1: [0.1017, 0.4005, 0.3784, 0.2019, 0.0101, 0.0],
        2: [0.6749, 0.2810, 0.0, 0.0441, 0.0, 0.0],
    }
    variances = sorted({v for vs in per_channel_v.values() for v in vs})
    weights = np.zeros((len(variances), 3))
    for c in range(3):
        for v, w in zip(per_channel_v[c], per_channel_w[c], strict=True):
            weights[variances.index(v), c] += w
    return GaussianTable(
        name="park_oh2009_forehead",
        variances_mm2=np.array(variances),
        weights=weights,
        source=(
            "Park, Oh, 'Measurement-based Face Rendering reflecting Positional Scattering "
            "Properties', 2009, figure 5 (forehead). As printed the G weights sum to 1.0926; "
            "use normalized_weights() for a profile that integrates to 1."
        ),
    )


PARK_OH_2009_FOREHEAD = _park_oh_forehead()
"""The seed paper's forehead fit, exactly as printed (G row sums to 1.0926)."""


def normalized_weights(table: GaussianTable) -> NDArray[np.float64]:
    """The table's weights scaled so that each channel sums to 1 (constraint eq. 2b)."""
    return table.weights / table.weights.sum(axis=0, keepdims=True)


@dataclass(frozen=True)
class ScatteringCoefficients:
    """Reduced scattering and absorption in mm^-1 (RGB) and relative index of refraction."""

    name: str
    sigma_s_prime: tuple[float, float, float]
    sigma_a: tuple[float, float, float]
    eta: float


JENSEN_2001: dict[str, ScatteringCoefficients] = {
    c.name: c
    for c in (
        ScatteringCoefficients("skin1", (0.74, 0.88, 1.01), (0.032, 0.17, 0.48), 1.3),
        ScatteringCoefficients("skin2", (1.09, 1.59, 1.79), (0.013, 0.070, 0.145), 1.3),
        ScatteringCoefficients("marble", (2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071), 1.5),
        ScatteringCoefficients("potato", (0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12), 1.3),
        ScatteringCoefficients("ketchup", (0.18, 0.07, 0.03), (0.061, 0.97, 1.45), 1.3),
        ScatteringCoefficients("wholemilk", (2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014), 1.3),
    )
}
"""Measured coefficients from Jensen, Marschner, Levoy, Hanrahan, 'A Practical Model for
Subsurface Light Transport', SIGGRAPH 2001, table 1 (mm^-1)."""
