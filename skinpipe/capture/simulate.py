"""Physically based simulator of single-pixel scattering captures (the ingest stage's truth).

It renders what the paper's camera saw: one projector pixel lights the skin with a small
smooth footprint, light exits with the region's radial profile R(r), each camera pixel
integrates the exitant light over its area, dark hair strands may shade the spot, and
each bracket adds photon and read noise above the sensor's black level, clips and
quantises (16-bit linear in the camera's colour space, or 8-bit sRGB). Exposure times go
into the manifest and/or the files' EXIF.

The truth is the *observed* profile: R convolved with the projector's footprint (what
any camera sees around the entry point), each channel normalised over the whole plane.
Every effect has a switch in :class:`CaptureSettings`; :data:`PRESETS` names the
defaults (``realistic``) and the simulator's earlier ones (``legacy``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import special

from ..errors import InputError
from ..fileio import atomic_write_json
from ..imageio import (
    ACESCG,
    check_colorspace,
    colorspace_matrix,
    convert_colorspace,
    write_ldr,
)
from ..profile.models import (
    dipole_profile,
    dipole_total_reflectance,
    disk_flux,
    disk_radius_mm,
    fit_error_eq2c,
    ring_areas_mm2,
    ring_edges_mm,
    sum_of_gaussians,
)
from ..profile.reference_data import (
    JENSEN_2001,
    PARK_OH_2009_FOREHEAD,
    ScatteringCoefficients,
    normalized_weights,
)

TRUTH_LINEAR = "lin_rec709_scene"
"""The colour space the true profiles are given in (scene-linear Rec.709)."""
CAMERA_SRGB = "srgb_rec709_scene"


def gaussian_blurred_radial(profile: Callable[[NDArray[np.float64]], NDArray[np.float64]],
                            radius_mm: NDArray[np.float64], sigma_mm: float,
                            nodes: int = 32) -> NDArray[np.float64]:
    """A radial profile f (mm^-2, (n,) -> (n, C)) convolved in the plane with an isotropic
    Gaussian of standard deviation ``sigma_mm``: (f * g)(r) = int_0^inf f(p) (p / s^2)
    exp(-(r - p)^2 / (2 s^2)) I0e(r p / s^2) dp (the angular integral of the 2D
    convolution, with the exponentially scaled Bessel function I0e), by Gauss-Legendre
    quadrature over [max(0, r - 7 s), r + 7 s] (32 nodes: within 1e-10 of the exact
    convolution of a sum of Gaussians). The total 2 pi int f r dr is unchanged."""
    r = np.asarray(radius_mm, dtype=np.float64).reshape(-1)
    if sigma_mm <= 0:
        return profile(r)
    s = float(sigma_mm)
    t, w = np.polynomial.legendre.leggauss(nodes)
    lo = np.maximum(r - 7.0 * s, 0.0)[:, None]
    half = 0.5 * (r[:, None] + 7.0 * s - lo)
    rho = lo + half * (t[None, :] + 1.0)
    kernel = (rho / s**2) * np.exp(-0.5 * (r[:, None] - rho) ** 2 / s**2) \
        * special.i0e(r[:, None] * rho / s**2) * half * w[None, :]
    values = profile(rho.reshape(-1)).reshape(*rho.shape, -1)
    return np.einsum("nk,nkc->nc", kernel, values)


@dataclass(frozen=True)
class RegionTruth:
    """A region's true profile in scene-linear Rec.709 RGB (:data:`TRUTH_LINEAR`).

    ``kind="gaussians"``: per-channel weights (each channel sums to 1) on
    ``variances_mm2``, scaled by ``albedo``. ``kind="dipole"``: Jensen et al.'s dipole
    for ``coefficients`` (its own total reflectance is the albedo). ``kind="rings"``:
    a measured profile as ring means (``ring_radius_mm``, ``ring_values``, mm^-2, in
    ACEScg as ``skinpipe fit`` reads a CSV), constant over each ring (edges halfway
    between centres): a ring of a light tracer's profile keeps the single scattering's
    spike whole. The observed profile is R convolved with the projector's footprint, a
    Gaussian of standard deviation ``footprint_sigma_mm`` (0: a point).
    """

    name: str
    kind: Literal["gaussians", "dipole", "rings"]
    variances_mm2: tuple[float, ...] = ()
    weights: tuple[tuple[float, float, float], ...] = ()
    albedo: tuple[float, float, float] = (1.0, 1.0, 1.0)
    coefficients: ScatteringCoefficients | None = None
    note: str = ""
    footprint_sigma_mm: float = 0.0
    ring_radius_mm: tuple[float, ...] = ()
    ring_values: tuple[tuple[float, float, float], ...] = ()

    def __post_init__(self) -> None:
        if self.kind == "rings":
            r = np.asarray(self.ring_radius_mm, dtype=np.float64)
            v = np.asarray(self.ring_values, dtype=np.float64)
            if r.ndim != 1 or r.size < 2 or v.shape != (r.size, 3) or not (
                    np.all(np.isfinite(r)) and np.all(np.isfinite(v))):
                raise InputError(f"region {self.name!r}: a ring profile needs two or more "
                                 "finite rings of three channels")
            if r[0] < 0 or np.any(np.diff(r) <= 0) or np.any(v < 0):
                raise InputError(f"region {self.name!r}: ring radii must rise from 0 or "
                                 "more and ring values must not be negative")

    def _ring_edges_mm(self) -> NDArray[np.float64]:
        """Every ring's edges, 0 first (as :func:`ring_edges_mm` reads ring samples)."""
        return np.concatenate([[0.0], ring_edges_mm(self.ring_radius_mm)])

    def _rings_rec709(self) -> NDArray[np.float64]:
        return np.asarray(self.ring_values, np.float64) @ colorspace_matrix(
            ACESCG, TRUTH_LINEAR).T

    def scattering_profile(self, radius_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """R(r): exitant light per unit incident flux, mm^-2, Rec.709 RGB, for a pencil
        of light (no footprint)."""
        if self.kind == "gaussians":
            return sum_of_gaussians(self.variances_mm2, np.array(self.weights), radius_mm) \
                * np.asarray(self.albedo)
        if self.kind == "rings":
            edges = self._ring_edges_mm()
            r = np.asarray(radius_mm, dtype=np.float64).reshape(-1)
            ring = np.searchsorted(edges, r, side="right") - 1
            inside = (ring >= 0) & (ring < edges.size - 1)
            out = np.zeros((r.size, 3))
            out[inside] = self._rings_rec709()[ring[inside]]
            return out
        assert self.coefficients is not None
        return dipole_profile(radius_mm, self.coefficients)

    def observed_profile(self, radius_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """R convolved with the footprint (Rec.709, mm^-2): what a camera sees. For a sum
        of Gaussians the footprint's variance adds to every term exactly; for rings too,
        each ring's share of the footprint centred at r being a difference of two
        non-central chi-square CDFs (the Marcum Q function)."""
        s = self.footprint_sigma_mm
        if self.kind == "gaussians":
            v = np.asarray(self.variances_mm2) + s * s
            return sum_of_gaussians(v, np.array(self.weights), radius_mm) \
                * np.asarray(self.albedo)
        if self.kind == "rings" and s > 0:
            return _rings_blurred(self._ring_edges_mm(), self._rings_rec709(),
                                  np.asarray(radius_mm, dtype=np.float64).reshape(-1), s)
        return gaussian_blurred_radial(self.scattering_profile, radius_mm, s)

    def acescg_profile(self, radius_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """The true profile as ingest reports it: the observed profile in ACEScg, each
        channel integrating to 1 over the plane."""
        m = colorspace_matrix(TRUTH_LINEAR, ACESCG)
        return (self.observed_profile(radius_mm) @ m.T) / (self.albedo_rec709() @ m.T)

    def disk_normalised_profile(
        self, radius_mm: NDArray[np.float64], disk_radius_mm: float
    ) -> NDArray[np.float64]:
        """The ACEScg truth scaled to integrate to 1 over a disk: what a perfect ingest of
        an image that sees nothing beyond ``disk_radius_mm`` would report without
        extrapolating the tail."""
        rf = np.linspace(0.0, disk_radius_mm, 8000)
        tf = self.acescg_profile(rf)
        disk = 2.0 * np.pi * np.trapezoid(tf * rf[:, None], rf, axis=0)
        return self.acescg_profile(radius_mm) / disk

    def share_beyond_mm(self, edge_mm: float) -> NDArray[np.float64]:
        """The share of each channel's flux (ACEScg) beyond ``edge_mm`` from the entry
        point (integrated to 400 mm; of the pencil profile: the footprint, a few
        hundredths of a mm, moves a share of order s^2 f' / f at the edge, < 1e-4)."""
        m = colorspace_matrix(TRUTH_LINEAR, ACESCG)
        rf = np.linspace(0.0, 400.0, 800001)
        tf = (self.scattering_profile(rf) @ m.T) * rf[:, None]
        inside = rf <= edge_mm
        return 1.0 - np.trapezoid(tf[inside], rf[inside], axis=0) / np.trapezoid(tf, rf,
                                                                                  axis=0)

    def profile_error(self, radius_mm: NDArray[np.float64], values: NDArray[np.float64],
                      lo_mm: float = 0.05, hi_mm: float = 4.0, over: str = "plane"
                      ) -> NDArray[np.float64]:
        """eq. 2c between ingested ``values`` (ring samples at ``radius_mm``) and the
        truth, over ``lo_mm``..``hi_mm``, per channel. ``over="plane"``: both integrate
        to 1 over the plane (ingest extrapolates the tail beyond the image); ``"disk"``:
        ``values`` rescaled to, and compared with the truth normalised over, the
        measured disk (the profile's shape alone, without the tail's extrapolation)."""
        r = np.asarray(radius_mm, dtype=np.float64)
        sel = (r >= lo_mm) & (r <= hi_mm)
        v = np.asarray(values, dtype=np.float64)
        if over == "plane":
            return fit_error_eq2c(r[sel], v[sel], self.acescg_profile(r[sel]))
        if over != "disk":
            raise ValueError(f"over must be 'plane' or 'disk', got {over!r}")
        v = v / disk_flux(r, v)
        return fit_error_eq2c(r[sel], v[sel],
                              self.disk_normalised_profile(r[sel], disk_radius_mm(r)))

    def albedo_rec709(self) -> NDArray[np.float64]:
        """Total diffuse reflectance per channel (Rec.709): the profile's integral."""
        if self.kind == "gaussians":
            return np.asarray(self.albedo, dtype=np.float64)
        if self.kind == "rings":
            return ring_areas_mm2(self.ring_radius_mm) @ self._rings_rec709()
        assert self.coefficients is not None
        return dipole_total_reflectance(self.coefficients)

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        if self.coefficients is None:
            doc.pop("coefficients")
        if self.kind != "rings":
            doc.pop("ring_radius_mm")
            doc.pop("ring_values")
        return doc


def ring_truth(path: str | Path) -> RegionTruth:
    """The region a measured PROFILE.csv describes (``kind="rings"``, named by the file's
    stem): its rows are ring means in ACEScg, mm^-2, as :func:`read_profile_csv` reads
    them. The capture's settings give it their footprint."""
    from ..fileio import check_path_name
    from ..profile.io import read_profile_csv

    profile = read_profile_csv(path)
    name = check_path_name(Path(path).stem, "profile name (the file's stem)")
    if not np.all(profile.values >= 0):
        raise InputError("a profile to simulate must not be negative anywhere", path)
    return RegionTruth(name, "rings", ring_radius_mm=tuple(map(float, profile.radius_mm)),
                       ring_values=tuple(tuple(map(float, v)) for v in profile.values),
                       note=f"rings of {Path(path).name}")


def _rings_blurred(edges_mm: NDArray[np.float64], values: NDArray[np.float64],
                   radius_mm: NDArray[np.float64], sigma_mm: float) -> NDArray[np.float64]:
    """Rings of constant ``values`` (n, C) between ``edges_mm`` (n + 1) convolved with a
    2D Gaussian of ``sigma_mm``, at ``radius_mm``: sum_i v_i P(e_i < |X| < e_i+1) with X
    ~ N((r, 0), s^2 I), P(|X| < e) = ncx2.cdf(e^2 / s^2, 2, r^2 / s^2) exactly. Edges
    more than 8 sigma from r are 0 or 1 (below 1e-14)."""
    from scipy.stats import ncx2

    out = np.zeros((radius_mm.size, values.shape[1]))
    for i, r in enumerate(radius_mm):
        lo, hi = np.searchsorted(edges_mm, [r - 8 * sigma_mm, r + 8 * sigma_mm])
        e = edges_mm[max(lo - 1, 0):hi + 1]
        cdf = ncx2.cdf((e / sigma_mm) ** 2, 2, (r / sigma_mm) ** 2)
        cdf[e > r + 8 * sigma_mm] = 1.0
        cdf[e < r - 8 * sigma_mm] = 0.0
        first = max(lo - 1, 0)
        out[i] = np.diff(cdf) @ values[first:first + e.size - 1]
    return out


MAX_SIZE_PX = 8192
MAX_HAIR_STRANDS = 200
"""A spot crossed by more strands is no capture anyone keeps (the paper re-shot spots a
single hair covered); each strand costs a pass over the image."""


@dataclass(frozen=True)
class CaptureSettings:
    """Camera and projector: geometry, footprint, sensor noise, encoding, brackets, hair.

    Each effect an ingest must handle has a switch here; the defaults are the
    ``realistic`` preset (:data:`PRESETS`):
    - ``mm_per_pixel`` 0.04: coarse pixels, the narrowest scattering (the forehead's
      first term with the footprint, sigma 0.092 mm) only 2.3 pixels wide in sigma;
    - ``footprint_sigma_mm`` 0.03: the projector pixel's smooth (Gaussian) footprint on
      the skin, part of the observed profile;
    - ``black_level`` 2048/65535: the sensor's offset in 16-bit files, so the short
      brackets' dark surround sits at the read-noise floor without being clipped at
      zero (0: the legacy sensor, which clips negative noise at zero, as 8-bit files
      are);
    - ``size_px`` 320: a 12.8 mm field, across which red light is still present at the
      border (5-11% of the red flux of the dipole regions lies beyond it);
    - ``hair_clearance_px`` (3, 40): hard-edged strands (1.5-3 px wide, passing 15% of
      the light, anti-aliased only by the pixel's area) whose nearest edge passes this
      far from the entry point (``hair_strands`` of them; a clearance below zero puts
      the entry point under the strand, e.g. (-1.2, -0.3));
    - ``camera_colorspace`` lin_p3d65_scene: the camera's linear space, named in the
      manifest (16-bit; 8-bit captures are sRGB-encoded Rec.709).
    """

    mm_per_pixel: float = 0.04
    size_px: int = 320
    footprint_sigma_mm: float = 0.03
    full_well_e: float = 20000.0
    read_noise_e: float = 4.0
    black_level: float = 2048.0 / 65535.0
    bits: Literal[8, 16] = 16
    exposures_s: tuple[float, ...] = (1 / 500, 1 / 125, 1 / 30, 1 / 8, 1 / 2)
    peak_fraction: float = 0.6
    hair_strands: int = 0
    hair_clearance_px: tuple[float, float] = (3.0, 40.0)
    camera_colorspace: str = "lin_p3d65_scene"
    exposure_in_manifest: bool = True
    image_format: Literal["tif", "png"] = "tif"

    def __post_init__(self) -> None:
        lo, hi = self.hair_clearance_px
        checks = {"mm_per_pixel": 0 < self.mm_per_pixel < 10,
                  "size_px": 32 <= self.size_px <= MAX_SIZE_PX,
                  "footprint_sigma_mm": 0 <= self.footprint_sigma_mm < 1,
                  "full_well_e": self.full_well_e > 0, "read_noise_e": self.read_noise_e >= 0,
                  "black_level": 0 <= self.black_level < 0.5,
                  "peak_fraction": 0 < self.peak_fraction <= 1,
                  "hair_strands": 0 <= self.hair_strands <= MAX_HAIR_STRANDS,
                  "hair_clearance_px": -3 <= lo <= hi,
                  "exposures_s": bool(self.exposures_s) and all(
                      math.isfinite(t) and t > 0 for t in self.exposures_s)}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise InputError("capture settings out of range: " + ", ".join(
                f"{k} = {getattr(self, k)!r}" for k in bad) + f" (size_px 32-{MAX_SIZE_PX}, "
                f"hair_strands 0-{MAX_HAIR_STRANDS}, mm_per_pixel in (0, 10), "
                "footprint_sigma_mm in [0, 1), black_level in [0, 0.5), hair_clearance_px "
                "low >= -3 and <= high)")
        check_colorspace(self.camera_colorspace)

    @property
    def colorspace(self) -> str:
        """The colour space of the files' code values."""
        return self.camera_colorspace if self.bits == 16 else CAMERA_SRGB


PRESETS: dict[str, CaptureSettings] = {
    "realistic": CaptureSettings(),
    "legacy": CaptureSettings(mm_per_pixel=0.025, footprint_sigma_mm=0.03 / math.sqrt(12.0),
                              black_level=0.0, hair_clearance_px=(4.5, 38.5),
                              camera_colorspace=TRUTH_LINEAR),
}
"""``realistic``: every effect of :class:`CaptureSettings` on (its defaults).
``legacy``: the simulator's earlier defaults (0.025 mm pixels, a 0.03 mm square
footprint, here as the Gaussian of the same variance, a sensor that clips noise at
zero, strands at least 4.5 px from the entry point, Rec.709 camera)."""


@dataclass
class SimulatedRegion:
    truth: RegionTruth
    entry_point_px: tuple[float, float]
    flux_in_frame: NDArray[np.float64]
    """The noise-free image's sum (ACEScg, code values per second): what an unbiased
    merge of the brackets adds up to."""
    files: list[str] = field(default_factory=list)


def spot_image(
    truth: RegionTruth, settings: CaptureSettings, centre_px: tuple[float, float],
) -> NDArray[np.float64]:
    """Noise-free image of the spot in the camera's linear space, per unit incident flux.

    Each pixel averages the observed profile over stratified points in its area (16 x
    16 near the entry point, 6 x 6 to 40 px, 2 x 2 beyond), from a radial table uniform
    in sqrt(r) (8000 steps: 0.1 um apart at 0.01 mm, 3 um at 9 mm; linear interpolation
    within 1e-5 of the narrowest profile here).
    """
    n = settings.size_px
    mmpp = settings.mm_per_pixel
    cx, cy = centre_px
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    dist = np.hypot(xx - cx, yy - cy)
    root_max = math.sqrt((float(dist.max()) + 1.0) * mmpp)
    table_u = np.linspace(0.0, root_max, 8000)
    table = truth.observed_profile(table_u**2) @ colorspace_matrix(
        TRUTH_LINEAR, settings.camera_colorspace if settings.bits == 16 else TRUTH_LINEAR).T
    out = np.zeros((n, n, 3))
    tiers = [(dist < 8, 16), ((dist >= 8) & (dist < 40), 6), (dist >= 40, 2)]
    for mask, s in tiers:
        py, px = np.nonzero(mask)
        if py.size == 0:
            continue
        grid = (np.arange(s) + 0.5) / s - 0.5
        acc = np.zeros((py.size, 3))
        for oy in grid:
            for ox in grid:
                root = np.sqrt(np.hypot(px + ox - cx, py + oy - cy) * mmpp)
                acc += np.stack([np.interp(root, table_u, table[:, c]) for c in range(3)],
                                axis=1)
        out[py, px] = acc / (s * s)
    return out


def hair_transmission(
    size_px: int, centre_px: tuple[float, float], strands: int,
    clearance_px: tuple[float, float], rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Transmission map of dark hair strands (1.5-3 px wide, passing 15% of the light)
    whose nearest edge passes ``clearance_px`` (low, high) from the entry point (below
    zero: over it). The edges are sharp, anti-aliased by the pixel's area only (a
    one-pixel ramp)."""
    yy, xx = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    trans = np.ones((size_px, size_px))
    for _ in range(strands):
        angle = rng.uniform(0, math.pi)
        width = rng.uniform(1.5, 3.0)
        offset = (rng.uniform(*clearance_px) + width / 2) * rng.choice([-1.0, 1.0])
        nx, ny = -math.sin(angle), math.cos(angle)
        d = np.abs((xx - centre_px[0]) * nx + (yy - centre_px[1]) * ny - offset)
        cover = np.clip(width / 2 + 0.5 - d, 0.0, 1.0)
        trans *= 1.0 - 0.85 * cover
    return trans


def expose(
    irradiance: NDArray[np.float64], exposure_s: float, settings: CaptureSettings,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Sensor response: photon (Poisson) and read noise above the black level, clipping,
    quantisation, encoding.

    ``irradiance`` is in code units per second (1 = full scale). Returns code values in
    [0, 1] as stored in the file (sRGB-encoded for 8-bit). With ``black_level`` 0 the
    noise is clipped at zero (the legacy sensor), as it is in an 8-bit file (processed:
    no offset).
    """
    electrons = np.clip(irradiance * exposure_s, 0.0, None) * settings.full_well_e
    signal = rng.poisson(np.minimum(electrons, 1e9)).astype(np.float64)
    signal += rng.normal(0.0, settings.read_noise_e, signal.shape)
    if settings.bits == 8:  # a processed file: the offset is gone, noise clipped at zero
        linear = np.clip(signal / settings.full_well_e, 0.0, 1.0)
        linear = np.clip(convert_colorspace(linear, TRUTH_LINEAR, CAMERA_SRGB), 0.0, 1.0)
    else:
        linear = np.clip(settings.black_level + signal / settings.full_well_e, 0.0, 1.0)
    top = (1 << settings.bits) - 1
    return np.rint(linear * top) / top


def simulate_region(
    truth: RegionTruth, settings: CaptureSettings, out_dir: Path, rng: np.random.Generator,
) -> tuple[SimulatedRegion, list[tuple[Path, NDArray[np.float64], float]]]:
    """Render one region's brackets in memory; returns the file plan (path, code values, t).
    ``truth`` gets the settings' footprint."""
    truth = replace(truth, footprint_sigma_mm=settings.footprint_sigma_mm)
    n = settings.size_px
    centre = (n / 2 + rng.uniform(-0.5, 0.5) - 0.5, n / 2 + rng.uniform(-0.5, 0.5) - 0.5)
    image = spot_image(truth, settings, centre)
    if settings.hair_strands:
        image *= hair_transmission(n, centre, settings.hair_strands,
                                   settings.hair_clearance_px, rng)[..., None]
    # Scale so that the brightest pixel reaches peak_fraction of full scale in the
    # shortest exposure: the set then spans the whole profile.
    scale = settings.peak_fraction / (image.max() * min(settings.exposures_s))
    space = settings.camera_colorspace if settings.bits == 16 else TRUTH_LINEAR
    flux = (image.reshape(-1, 3).sum(axis=0) * scale) @ colorspace_matrix(space, ACESCG).T
    plan = []
    for i, t in enumerate(settings.exposures_s):
        code = expose(image * scale, t, settings, rng)
        plan.append((out_dir / truth.name / f"e{i}.{settings.image_format}", code, t))
    return SimulatedRegion(truth, centre, flux), plan


def simulate_capture_set(
    truths: list[RegionTruth], out_dir: str | Path, settings: CaptureSettings | dict[str, Any],
    subject: str = "simulated", seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Write a capture set (capture.json, images) plus truth.json with the true profiles.

    ``settings`` may map region names to their own :class:`CaptureSettings` (a
    ``"default"`` entry for the rest), so one subject can mix 16-bit TIFF and 8-bit PNG.
    truth.json holds per region the truth (with its footprint), the entry point, the
    settings and the frame's noise-free flux (ACEScg, code values per second).
    """
    out = Path(out_dir)
    per_region = settings if isinstance(settings, dict) else {"default": settings}
    default = per_region.get("default", CaptureSettings())
    mmpp = {s.mm_per_pixel for s in per_region.values()}
    if len(mmpp) != 1:
        raise InputError("all regions of one capture set share mm_per_pixel")
    spaces = {s.colorspace for s in per_region.values()}
    if len(spaces) != 1:
        raise InputError("all regions of one capture set share the camera colour space "
                         "(and bits: 8 = sRGB)")
    rng = np.random.default_rng(seed)
    manifest: dict[str, Any] = {"subject": subject, "mm_per_pixel": default.mm_per_pixel,
                                "camera_colorspace": default.colorspace, "regions": {}}
    truth_doc: dict[str, Any] = {"subject": subject, "seed": seed, "truth_linear": TRUTH_LINEAR,
                                 "regions": {}}
    for truth in truths:
        st = per_region.get(truth.name, default)
        sim, plan = simulate_region(truth, st, out, rng)
        images = []
        for path, code, t in plan:
            write_ldr(path, code, st.bits, {"ExposureTime": float(t)})
            entry = {"file": f"{truth.name}/{path.name}"}
            if st.exposure_in_manifest:
                entry["exposure_s"] = float(t)
            images.append(entry)
        manifest["regions"][truth.name] = {"images": images}
        truth_doc["regions"][truth.name] = {
            "truth": sim.truth.to_json(), "entry_point_px": list(sim.entry_point_px),
            "flux_in_frame": sim.flux_in_frame.tolist(), "settings": asdict(st),
        }
        if progress is not None:
            progress(f"simulated {truth.name}: {len(plan)} brackets, entry point "
                     f"({sim.entry_point_px[0]:.2f}, {sim.entry_point_px[1]:.2f}) px")
    atomic_write_json(out / "capture.json", manifest)
    atomic_write_json(out / "truth.json", truth_doc)
    return truth_doc


def read_truth(path: str | Path) -> dict[str, RegionTruth]:
    """RegionTruth per region from a truth.json written by :func:`simulate_capture_set`."""
    doc = json.loads(Path(path).read_text(encoding="utf-8"))
    out = {}
    for name, entry in doc["regions"].items():
        t = dict(entry["truth"])
        if t.get("coefficients"):
            c = t["coefficients"]
            t["coefficients"] = ScatteringCoefficients(c["name"], tuple(c["sigma_s_prime"]),
                                                       tuple(c["sigma_a"]), c["eta"])
        t["variances_mm2"] = tuple(t.get("variances_mm2", ()))
        t["weights"] = tuple(tuple(w) for w in t.get("weights", ()))
        t["albedo"] = tuple(t.get("albedo", (1.0, 1.0, 1.0)))
        t["ring_radius_mm"] = tuple(t.get("ring_radius_mm", ()))
        t["ring_values"] = tuple(tuple(v) for v in t.get("ring_values", ()))
        out[name] = RegionTruth(**t)
    return out


def _varied(base: str, name: str, s_scale: tuple[float, float, float],
            a_scale: tuple[float, float, float]) -> ScatteringCoefficients:
    c = JENSEN_2001[base]
    return ScatteringCoefficients(
        name, tuple(s * f for s, f in zip(c.sigma_s_prime, s_scale, strict=True)),  # type: ignore[arg-type]
        tuple(a * f for a, f in zip(c.sigma_a, a_scale, strict=True)), c.eta)  # type: ignore[arg-type]


def sample_subject_truths() -> list[RegionTruth]:
    """The six regions of the bundled sample subject, each physically motivated."""
    fh = PARK_OH_2009_FOREHEAD
    w = normalized_weights(fh)
    return [
        RegionTruth("forehead", "gaussians", tuple(fh.variances_mm2.tolist()),
                    tuple(tuple(row) for row in w.tolist()), (0.55, 0.40, 0.32),
                    note="Park & Oh 2009 figure 5 forehead fit, G row renormalised to 1"),
        RegionTruth("lips", "dipole", coefficients=_varied("skin1", "lips", (0.85, 0.85, 0.85),
                                                           (1.0, 1.8, 1.6)),
                    note="skin1 with more blood absorption in G and B, thinner scattering layer"),
        RegionTruth("chin", "dipole", coefficients=_varied("skin2", "chin", (1.05, 1.05, 1.05),
                                                           (1.0, 1.0, 1.0)),
                    note="skin2, slightly denser dermis"),
        RegionTruth("cheekbone", "dipole",
                    coefficients=_varied("skin2", "cheekbone", (1.15, 1.1, 1.1),
                                         (0.9, 0.9, 0.9)),
                    note="skin2 over bone: thin tissue, more scattering, less absorption"),
        RegionTruth("cheek", "dipole", coefficients=_varied("skin1", "cheek", (1.0, 1.0, 1.0),
                                                            (1.0, 1.25, 1.1)),
                    note="skin1 with a flush (more haemoglobin absorption in G)"),
        RegionTruth("nose", "dipole", coefficients=_varied("skin1", "nose", (1.3, 1.25, 1.2),
                                                           (1.1, 1.1, 1.1)),
                    note="skin1, oily and dense: more scattering close to the entry point"),
    ]
