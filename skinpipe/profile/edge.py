"""What a hard shadow edge shows of a diffusion profile: its edge-spread function.

Under a light that stops at a straight edge (light on x < 0), the radiance at x is the
profile integrated over the lit half-plane: for a radially symmetric profile R, with
light entering at q and leaving at p,

    L(x) = int_{q_x < 0} R(|p - q|) dq = E(-x),   E(t) = int_{u_x <= t} R(|u|) du,

E the edge-spread function (the profile's cumulative along one axis; E(t) + E(-t) is the
profile's total). How wide the edge looks, and how much light reaches into the shadow,
are properties of E, not of the profile's values: a profile fitted through its values
can spread the same energy differently (an entry spike of single scattering holding a
fifth to a half of the light, and the tails paying for it). The fit therefore matches
E as well (docs/fit.md), and reports:

- the edge-spread error: the largest |E_measured - E_fitted| over the measured range
  beyond the central two rings (the measurement's resolution), as a share of the
  plateau (the total),
- the 10-90% edge width, measured and fitted,
- the light in the shadow, int_0^inf E(-x) dx, fitted over measured.

E of a sum of Gaussians is closed form: sum_i w_i Phi(t / sqrt(v_i)). E of a sampled
profile takes each sample as the radiance of its ring (:func:`~.models.ring_areas_mm2`:
edges midway between samples), exact for ring averages: each ring's share of the
half-plane is a difference of two circular segments.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import erfc

from .models import ring_edges_mm

FloatArray = NDArray[np.float64]


def disc_share_below(radius_mm: ArrayLike, t_mm: ArrayLike) -> FloatArray:
    """Area of the disc |u| <= R with u_x <= t (mm^2), broadcast over R and t."""
    r = np.asarray(radius_mm, dtype=np.float64)
    t = np.asarray(t_mm, dtype=np.float64)
    # t clipped to the disc first: t / R may not overflow where R is (next to) zero
    c = np.clip(t, -r, r) / np.maximum(r, 1e-300)
    return r**2 * (math.pi - np.arccos(c)) + np.clip(t, -r, r) * r * np.sqrt(1.0 - c**2)


def ring_areas_beyond(radius_mm: ArrayLike, t_mm: ArrayLike) -> FloatArray:
    """(m, n): the area (mm^2) of each of the n rings of ``radius_mm`` beyond the line
    u_x = t, for each of the m ``t_mm``: :func:`spread_beyond_rings` is this times the
    ring radiances."""
    outer = ring_edges_mm(np.asarray(radius_mm, dtype=np.float64))
    inner = np.concatenate([[0.0], outer[:-1]])
    area = math.pi * (outer**2 - inner**2)
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1, 1)
    return area[None, :] - (disc_share_below(outer[None, :], t)
                            - disc_share_below(inner[None, :], t))


def spread_beyond_rings(radius_mm: ArrayLike, values: ArrayLike, t_mm: ArrayLike,
                        chunk: int = 256) -> FloatArray:
    """1 - E(t) of a sampled profile: the light beyond the line u_x = t, per channel
    ((m,) or (m, c) for ``values`` (n,) or (n, c)); each sample the radiance of its ring."""
    p = np.asarray(values, dtype=np.float64)
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1)
    out = np.empty((t.size, *p.shape[1:]))
    for s in range(0, t.size, chunk):
        out[s:s + chunk] = ring_areas_beyond(radius_mm, t[s:s + chunk]) @ p
    return out


def spread_beyond_gaussians(variances_mm2: ArrayLike, weights: ArrayLike, t_mm: ArrayLike
                            ) -> FloatArray:
    """1 - E(t) of sum_i w_i G(v_i): sum_i w_i Phi(-t / sqrt(v_i)), per channel."""
    v = np.asarray(variances_mm2, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    t = np.asarray(t_mm, dtype=np.float64).reshape(-1)
    return 0.5 * erfc(t[:, None] / np.sqrt(2.0 * v[None, :])) @ w


def edge_positions_mm(radius_mm: ArrayLike) -> FloatArray:
    """Where an edge is compared: the rings' edges from 0 to the measured disk's,
    mirrored (E is symmetric about its half-height)."""
    outer = ring_edges_mm(radius_mm)
    return np.concatenate([-outer[::-1], [0.0], outer])


def edge_width_mm(t_mm: FloatArray, beyond: FloatArray) -> FloatArray:
    """The 10-90% width of an edge from its light beyond each position (ascending
    ``t_mm``), per channel: where 1 - E crosses 90% and 10% of its plateau."""
    b = beyond.reshape(t_mm.size, -1)
    plateau = b[0]
    out = np.empty(b.shape[1])
    for c in range(b.shape[1]):
        f = b[:, c] / plateau[c]  # falling from 1 to 0
        out[c] = float(np.interp(-0.1, -f, t_mm) - np.interp(-0.9, -f, t_mm))
    return out


def shadow_light(t_mm: FloatArray, beyond: FloatArray) -> FloatArray:
    """int_0^inf (1 - E(t)) dt, per channel: the light a lit half-plane sends into its
    shadow (mm times the radiance's unit)."""
    b = beyond.reshape(t_mm.size, -1)
    keep = t_mm >= 0
    return np.trapezoid(b[keep], t_mm[keep], axis=0)


def ring_means_of_gaussians(radius_mm: ArrayLike, variances_mm2: ArrayLike,
                            weights: ArrayLike) -> FloatArray:
    """sum_i w_i G(v_i) averaged over each sample's ring (exact: G's light within r is
    1 - exp(-r^2 / 2v)), per channel."""
    outer = ring_edges_mm(radius_mm)
    inner = np.concatenate([[0.0], outer[:-1]])
    v = np.asarray(variances_mm2, dtype=np.float64)[None, :]
    light = np.exp(-inner[:, None] ** 2 / (2 * v)) - np.exp(-outer[:, None] ** 2 / (2 * v))
    area = math.pi * (outer**2 - inner**2)
    return (light / area[:, None]) @ np.asarray(weights, dtype=np.float64)


def edge_report(radius_mm: ArrayLike, values: ArrayLike, variances_mm2: ArrayLike,
                weights: ArrayLike) -> dict[str, FloatArray]:
    """The fit's edge measures against the measured profile's, per channel:
    ``edge_error`` (largest difference of E over the measured range, beyond the central
    two rings, as a share of the measured plateau), ``edge_width_mm`` and
    ``edge_width_measured_mm`` (10-90%), ``shadow_light_ratio`` (fitted over measured).
    Both are taken over the measured disc, the fit's light as its rings' means (what a
    measurement of it would give: light the image did not hold is in neither), and the
    fit scaled to the measured light within the disc."""
    r = np.asarray(radius_mm, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64).reshape(r.size, -1)
    t = edge_positions_mm(r)
    measured = spread_beyond_rings(r, p, t)
    plateau = measured[0]
    model = spread_beyond_rings(r, ring_means_of_gaussians(r, variances_mm2, weights), t)
    fitted = model * (plateau / np.maximum(model[0], 1e-300))[None, :]
    # the central two rings are the measurement's resolution: inside them no sample says
    # where the light is (an entry spike's disc of one ring or its Gaussian)
    keep = np.abs(t) >= ring_edges_mm(r)[min(1, r.size - 1)] - 1e-12
    error = np.abs(fitted - measured)[keep].max(axis=0) / np.maximum(plateau, 1e-300)
    return {"edge_error": error, "edge_width_mm": edge_width_mm(t, fitted),
            "edge_width_measured_mm": edge_width_mm(t, measured),
            "shadow_light_ratio": shadow_light(t, fitted) / np.maximum(
                shadow_light(t, measured), 1e-300)}
