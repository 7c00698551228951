"""An independent Monte Carlo light tracer for a homogeneous, semi-infinite slab: the
truth skinpipe's physics tests hold it to. Nothing of skinpipe is imported.

The medium fills z < 0 (mm): scattering and absorption coefficients ``sigma_s``,
``sigma_a`` (per mm), Henyey-Greenstein phase function of anisotropy ``g``, refractive
index ``eta`` against air above (``eta = 1``: index-matched, no boundary). Light arrives
from above as a pencil at the origin (``theta_in_deg`` from the normal); the Fresnel
share of it (unpolarised, smooth surface) is reflected away, the rest refracts in.

Photons (packets of weight) take exponential free paths; at each collision the weight
times the single-scattering albedo is the scattered share. What a camera straight above
sees is estimated at every collision (a collision estimator with next-event estimation
toward +z, as Jensen et al. 2001 and Mitsuba's volpath do for a camera): the photon's
weight times the albedo, times the phase function toward +z, times the attenuation
exp(-sigma_t depth) on the way up, times the boundary's transmission at normal
incidence over eta^2 (radiance crosses a boundary as L/n^2), added to the ring of radius
sqrt(x^2 + y^2). Summed over photons and divided by each ring's area and the number of
photons, that is the exit radiance seen from straight above per unit incident power:
the profile the paper measures. A photon that reaches the surface from below is
reflected with the Fresnel probability (totally beyond the critical angle), else it
leaves. Russian roulette ends light photons without bias.

Checked by tests/physics/test_light_tracer.py against closed forms (the single
scattering of an index-matched medium; the total diffuse reflectance of an isotropic,
index-matched half-space, Chandrasekhar's H-function) and, where Mitsuba 3 is
installed, benchmarks/bench_physics.py holds it to Mitsuba's volpath.

    python -m tests.physics.light_tracer   # rewrites tests/fixtures/physics/*.csv
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class Medium:
    """A homogeneous medium; lengths in mm."""

    sigma_s: float
    sigma_a: float
    g: float = 0.0
    eta: float = 1.0

    @property
    def sigma_t(self) -> float:
        return self.sigma_s + self.sigma_a

    @property
    def albedo(self) -> float:
        return self.sigma_s / self.sigma_t


def fresnel(cos_i: NDArray[np.float64], eta_i: float, eta_t: float) -> NDArray[np.float64]:
    """Unpolarised Fresnel reflectance of a smooth boundary, light going from index
    ``eta_i`` to ``eta_t`` at incidence cosine ``cos_i`` (1 beyond the critical angle)."""
    cos_i = np.clip(np.abs(cos_i), 0.0, 1.0)
    sin_t = eta_i / eta_t * np.sqrt(np.maximum(0.0, 1.0 - cos_i**2))
    total = sin_t >= 1.0
    cos_t = np.sqrt(np.maximum(0.0, 1.0 - sin_t**2))
    rs = (eta_i * cos_i - eta_t * cos_t) / np.maximum(eta_i * cos_i + eta_t * cos_t, 1e-300)
    rp = (eta_t * cos_i - eta_i * cos_t) / np.maximum(eta_t * cos_i + eta_i * cos_t, 1e-300)
    return np.where(total, 1.0, 0.5 * (rs**2 + rp**2))


def henyey_greenstein(cos_theta: NDArray[np.float64], g: float) -> NDArray[np.float64]:
    """The HG phase function (per steradian)."""
    return (1 - g * g) / (4 * math.pi * (1 + g * g - 2 * g * cos_theta) ** 1.5)


def _sample_cos(u: NDArray[np.float64], g: float) -> NDArray[np.float64]:
    if abs(g) < 1e-6:
        return 2 * u - 1
    s = (1 - g * g) / (1 - g + 2 * g * u)
    return np.clip((1 + g * g - s * s) / (2 * g), -1.0, 1.0)


def _turn(d: NDArray[np.float64], cos_t: NDArray[np.float64], phi: NDArray[np.float64]
          ) -> NDArray[np.float64]:
    """Directions at angle acos(cos_t) from ``d`` (unit, (N, 3)), azimuth ``phi``."""
    sin_t = np.sqrt(np.maximum(0.0, 1 - cos_t**2))
    # an orthonormal frame about d (Duff et al. 2017)
    sign = np.where(d[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + d[:, 2])
    b = d[:, 0] * d[:, 1] * a
    t1 = np.stack([1 + sign * d[:, 0] ** 2 * a, sign * b, -sign * d[:, 0]], axis=1)
    t2 = np.stack([b, sign + d[:, 1] ** 2 * a, -d[:, 1]], axis=1)
    out = (sin_t * np.cos(phi))[:, None] * t1 + (sin_t * np.sin(phi))[:, None] * t2 \
        + cos_t[:, None] * d
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def _roulette(rng: np.random.Generator, w: NDArray[np.float64], *state: NDArray[Any]
              ) -> tuple[NDArray[Any], ...]:
    """Russian roulette on photons of weight below 1e-3: one in ten goes on, ten times
    heavier (unbiased); ``state`` (their positions, directions) and ``w`` of those left."""
    low = w < 1e-3
    if not low.any():
        return (*state, w)
    live = ~low | (rng.random(w.size) < 0.1)
    w = np.where(low, w * 10.0, w)
    return (*(a[live] for a in state), w[live])


@dataclass
class Tally:
    """What a trace gathered, per unit incident power: ``ring_sums`` (the up-radiance
    estimator summed per ring, not yet divided by area), the rings' outer edges (mm),
    ``total`` (the estimator summed everywhere: the exit radiance seen from above under
    uniform unit irradiance across the incident beam's cross-section), ``photons``."""

    edges_mm: NDArray[np.float64]
    ring_sums: NDArray[np.float64]
    total: float
    photons: int

    def radiance(self) -> NDArray[np.float64]:
        """Mean up-radiance in each ring, per unit incident power, per mm^2 and sr."""
        inner = np.concatenate([[0.0], self.edges_mm[:-1]])
        return self.ring_sums / (math.pi * (self.edges_mm**2 - inner**2)) / self.photons

    def centres(self) -> NDArray[np.float64]:
        inner = np.concatenate([[0.0], self.edges_mm[:-1]])
        return 0.5 * (inner + self.edges_mm)


def trace(medium: Medium, photons: int, edges_mm: NDArray[np.float64],
          theta_in_deg: float = 0.0, seed: int = 0, batch: int = 200_000) -> Tally:
    """A pencil of unit power at the origin, ``photons`` packets (see the module)."""
    rng = np.random.default_rng(seed)
    edges = np.asarray(edges_mm, np.float64)
    sums = np.zeros(edges.size)
    total = 0.0
    st, alb, g, eta = medium.sigma_t, medium.albedo, medium.g, medium.eta
    t_up = (1.0 - float(fresnel(np.array([1.0]), eta, 1.0)[0])) / eta**2
    cos_in = math.cos(math.radians(theta_in_deg))
    t_in = 1.0 - float(fresnel(np.array([cos_in]), 1.0, eta)[0])
    sin_t = math.sin(math.radians(theta_in_deg)) / eta
    start_dir = np.array([sin_t, 0.0, -math.sqrt(1 - sin_t**2)])
    done = 0
    while done < photons:
        n = min(batch, photons - done)
        done += n
        pos = np.zeros((n, 3))
        d = np.tile(start_dir, (n, 1))
        w = np.full(n, t_in)
        while w.size:
            step = -np.log(1.0 - rng.random(w.size)) / st
            pos = pos + step[:, None] * d
            hit = pos[:, 2] > 0
            if hit.any():  # at the surface from below: reflected (no collision) or gone
                idx = np.flatnonzero(hit)
                back = pos[idx, 2] / d[idx, 2]
                pos[idx] -= back[:, None] * d[idx]
                pos[idx, 2] = 0.0
                reflect = rng.random(idx.size) < fresnel(d[idx, 2], eta, 1.0)
                d[idx[reflect], 2] *= -1.0
                keep = np.ones(w.size, bool)
                keep[idx[~reflect]] = False
                pos, d, w, hit = pos[keep], d[keep], w[keep], hit[keep]
            c = np.flatnonzero(~hit)  # collisions: what each sends straight up, then on
            up = w[c] * alb * henyey_greenstein(d[c, 2], g) * np.exp(st * pos[c, 2]) * t_up
            ring = np.searchsorted(edges, np.hypot(pos[c, 0], pos[c, 1]), side="right")
            inside = ring < edges.size
            sums += np.bincount(ring[inside], up[inside], minlength=edges.size)[:edges.size]
            total += float(up.sum())
            w[c] *= alb
            d[c] = _turn(d[c], _sample_cos(rng.random(c.size), g),
                         2 * math.pi * rng.random(c.size))
            pos, d, w = _roulette(rng, w, pos, d)
    return Tally(edges, sums, total / photons, photons)


def trace_slab_from_below(medium: Medium, thickness_mm: float, photons: int,
                          seed: int = 0, batch: int = 200_000) -> float:
    """What a camera straight above an index-matched slab (0 > z > -thickness) sees of a
    normal pencil of unit power entering its underside: the scattered light's
    up-radiance summed over the top surface (the collision estimator of :func:`trace`),
    i.e. the exit radiance under uniform unit irradiance from below. The unscattered
    beam, a delta in direction, is left out. Photons leaving either face are gone."""
    if medium.eta != 1.0:
        raise ValueError("the slab tracer is index-matched only")
    rng = np.random.default_rng(seed)
    st, alb, g = medium.sigma_t, medium.albedo, medium.g
    total, done = 0.0, 0
    while done < photons:
        n = min(batch, photons - done)
        done += n
        z = np.full(n, -float(thickness_mm))
        d = np.tile([0.0, 0.0, 1.0], (n, 1))
        w = np.ones(n)
        while w.size:
            z = z + (-np.log(1.0 - rng.random(w.size)) / st) * d[:, 2]
            inside = (z < 0.0) & (z > -thickness_mm)
            z, d, w = z[inside], d[inside], w[inside]
            total += float((w * alb * henyey_greenstein(d[:, 2], g) * np.exp(st * z)).sum())
            w = w * alb
            d = _turn(d, _sample_cos(rng.random(w.size), g), 2 * math.pi * rng.random(w.size))
            z, d, w = _roulette(rng, w, z, d)
    return total / photons


def single_scattering_index_matched(medium: Medium) -> float:
    """Closed form of the up-radiance's total from first collisions only (eta = 1, a
    normal pencil): sum over depth of sigma_s p(-1 -> +1) e^{-2 sigma_t z} dz =
    albedo p_HG(cos = -1) / 2. The tracer's first collision contributes exactly this."""
    return medium.albedo * float(henyey_greenstein(np.array([-1.0]), medium.g)[0]) / 2.0


# The media of skinpipe's physics tests: per mm, R, G, B (Jensen et al. 2001, table 2:
# skin1 and marble; "forward" is skin1's reduced scattering with g = 0.8).
MEDIA: dict[str, tuple[list[float], list[float], float, float]] = {
    "skin1": ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48], 0.0, 1.0),
    "skin1_eta1.4": ([0.74, 0.88, 1.01], [0.032, 0.17, 0.48], 0.0, 1.4),
    "forward": ([0.74 / 0.2, 0.88 / 0.2, 1.01 / 0.2], [0.032, 0.17, 0.48], 0.8, 1.0),
    "marble": ([2.19, 2.62, 3.00], [0.0021, 0.0041, 0.0071], 0.0, 1.5),
}
RING_MM = 0.025
"""Ring width of the pencil profiles: the paper's pixel on the skin (0.02 mm), rounded."""


def medium(name: str, channel: int) -> Medium:
    s, a, g, eta = MEDIA[name]
    return Medium(s[channel], a[channel], g, eta)


def profile_edges(name: str) -> NDArray[np.float64]:
    """Ring edges far enough for the medium: beyond them less than 1e-4 of the light."""
    s, a, g, _ = MEDIA[name]
    sigma_tr = min(math.sqrt(3 * ai * (ai + si * (1 - g))) for si, ai in zip(s, a, strict=True))
    radius = min(12.0 / sigma_tr, 80.0)
    return RING_MM * np.arange(1, int(radius / RING_MM) + 1)


PROFILE_PHOTONS = 500_000
LIT_PHOTONS = 200_000
LIT_ANGLES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)


def write_fixtures(out: Path, names: tuple[str, ...] = tuple(MEDIA)) -> None:
    """Every medium's pencil profile as a profile CSV (rings, R, G, B; each channel
    normalised to integrate to 1 over the plane, as ``skinpipe fit`` takes a profile,
    the absolute level kept in totals.json), and its lit level against incidence."""
    out.mkdir(parents=True, exist_ok=True)
    totals = {}
    for name in names:
        edges = profile_edges(name)
        inner = np.concatenate([[0.0], edges[:-1]])
        area = math.pi * (edges**2 - inner**2)
        cols, chans = [], []
        for c in range(3):
            tally = trace(medium(name, c), PROFILE_PHOTONS, edges, seed=100 + c)
            radiance = tally.radiance()
            cols.append(radiance / float((radiance * area).sum()))
            lit = [trace(medium(name, c), LIT_PHOTONS, np.array([1.0]), theta,
                         seed=7 + c).total for theta in LIT_ANGLES_DEG]
            chans.append({"up_radiance_total": tally.total,
                          "within_rings": float((radiance * area).sum()),
                          "lit_up_radiance": dict(zip(map(str, LIT_ANGLES_DEG), lit,
                                                      strict=True))})
            print(f"{name} {'RGB'[c]}: total {tally.total:.5f}", flush=True)
        rows = np.column_stack([0.5 * (inner + edges), *cols])
        np.savetxt(out / f"{name}.csv", rows, delimiter=",", fmt="%.8g",
                   header="radius_mm,R,G,B", comments="")
        totals[name] = {"medium": MEDIA[name], "photons": PROFILE_PHOTONS,
                        "lit_photons": LIT_PHOTONS, "channels": chans}
    import json

    path = out / "totals.json"
    old = json.loads(path.read_text()) if path.is_file() else {}
    path.write_text(json.dumps({**old, **totals}, indent=1) + "\n")


def main() -> None:
    """Rewrite tests/fixtures/physics/ (media named on the command line, or all)."""
    import sys
    from pathlib import Path

    names = tuple(sys.argv[1:]) or tuple(MEDIA)
    write_fixtures(Path(__file__).resolve().parents[1] / "fixtures" / "physics", names)


if __name__ == "__main__":
    main()
