"""Physically based simulator of single-pixel scattering captures (the ingest stage's truth).

It renders what the paper's camera saw: one projector pixel (a small square footprint)
lights the skin, light exits with the region's radial profile R(r), each camera pixel
integrates the exitant light over its area, dark hair strands may shade the spot, and
each bracket adds photon and read noise, clips and quantises (16-bit linear or 8-bit
sRGB). Exposure times go into the manifest and/or the files' EXIF.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from ..errors import InputError
from ..fileio import atomic_write_json
from ..imageio import ACESCG, colorspace_matrix, convert_colorspace, write_ldr
from ..profile.models import (
    dipole_profile,
    dipole_total_reflectance,
    disk_radius_mm,
    fit_error_eq2c,
    ring_areas_mm2,
    sum_of_gaussians,
)
from ..profile.reference_data import (
    JENSEN_2001,
    PARK_OH_2009_FOREHEAD,
    ScatteringCoefficients,
    normalized_weights,
)

CAMERA_LINEAR = "lin_rec709_scene"
CAMERA_SRGB = "srgb_rec709_scene"


@dataclass(frozen=True)
class RegionTruth:
    """A region's true profile in camera-linear RGB (Rec.709 primaries).

    ``kind="gaussians"``: per-channel weights (each channel sums to 1) on
    ``variances_mm2``, scaled by ``albedo``. ``kind="dipole"``: Jensen et al.'s dipole
    for ``coefficients`` (its own total reflectance is the albedo).
    """

    name: str
    kind: Literal["gaussians", "dipole"]
    variances_mm2: tuple[float, ...] = ()
    weights: tuple[tuple[float, float, float], ...] = ()
    albedo: tuple[float, float, float] = (1.0, 1.0, 1.0)
    coefficients: ScatteringCoefficients | None = None
    note: str = ""

    def camera_profile(self, radius_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """Exitant light per unit incident flux, R(r) in mm^-2, camera-linear RGB."""
        if self.kind == "gaussians":
            return sum_of_gaussians(self.variances_mm2, np.array(self.weights), radius_mm) \
                * np.asarray(self.albedo)
        assert self.coefficients is not None
        return dipole_profile(radius_mm, self.coefficients)

    def acescg_profile(self, radius_mm: NDArray[np.float64]) -> NDArray[np.float64]:
        """The true profile as ingest reports it: ACEScg, each channel integrating to 1."""
        m = colorspace_matrix(CAMERA_LINEAR, ACESCG)
        return (self.camera_profile(radius_mm) @ m.T) / (self.camera_albedo() @ m.T)

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
        point (integrated to 400 mm)."""
        rf = np.linspace(0.0, 400.0, 800001)
        tf = self.acescg_profile(rf) * rf[:, None]
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
        v = v / (v * ring_areas_mm2(r)[:, None]).sum(axis=0)
        return fit_error_eq2c(r[sel], v[sel],
                              self.disk_normalised_profile(r[sel], disk_radius_mm(r)))

    def camera_albedo(self) -> NDArray[np.float64]:
        if self.kind == "gaussians":
            return np.asarray(self.albedo, dtype=np.float64)
        assert self.coefficients is not None
        return dipole_total_reflectance(self.coefficients)

    def to_json(self) -> dict[str, Any]:
        doc = asdict(self)
        if self.coefficients is None:
            doc.pop("coefficients")
        return doc


MAX_SIZE_PX = 8192
MAX_HAIR_STRANDS = 200
"""A spot crossed by more strands is no capture anyone keeps (the paper re-shot spots a
single hair covered); each strand costs a pass over the image."""


@dataclass(frozen=True)
class CaptureSettings:
    """Camera and projector: geometry, sensor noise, encoding, brackets."""

    mm_per_pixel: float = 0.025
    size_px: int = 320
    footprint_mm: float = 0.03
    full_well_e: float = 20000.0
    read_noise_e: float = 4.0
    bits: Literal[8, 16] = 16
    exposures_s: tuple[float, ...] = (1 / 500, 1 / 125, 1 / 30, 1 / 8, 1 / 2)
    peak_fraction: float = 0.6
    hair_strands: int = 0
    exposure_in_manifest: bool = True
    image_format: Literal["tif", "png"] = "tif"

    def __post_init__(self) -> None:
        checks = {"mm_per_pixel": 0 < self.mm_per_pixel < 10,
                  "size_px": 32 <= self.size_px <= MAX_SIZE_PX,
                  "footprint_mm": 0 <= self.footprint_mm < 10,
                  "full_well_e": self.full_well_e > 0, "read_noise_e": self.read_noise_e >= 0,
                  "peak_fraction": 0 < self.peak_fraction <= 1,
                  "hair_strands": 0 <= self.hair_strands <= MAX_HAIR_STRANDS,
                  "exposures_s": bool(self.exposures_s) and all(
                      math.isfinite(t) and t > 0 for t in self.exposures_s)}
        bad = [k for k, ok in checks.items() if not ok]
        if bad:
            raise InputError("capture settings out of range: " + ", ".join(
                f"{k} = {getattr(self, k)!r}" for k in bad) + f" (size_px 32-{MAX_SIZE_PX}, "
                f"hair_strands 0-{MAX_HAIR_STRANDS}, mm_per_pixel in (0, 10))")

    @property
    def colorspace(self) -> str:
        return CAMERA_LINEAR if self.bits == 16 else CAMERA_SRGB


@dataclass
class SimulatedRegion:
    truth: RegionTruth
    entry_point_px: tuple[float, float]
    files: list[str] = field(default_factory=list)


def spot_image(
    truth: RegionTruth, settings: CaptureSettings, centre_px: tuple[float, float],
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Camera-linear irradiance image of the spot for unit incident flux (per mm^2).

    Each pixel averages R(|x - c - f|) over stratified points x in the pixel and f in the
    projector pixel's square footprint; more points where the profile is peaked.
    """
    n = settings.size_px
    mmpp = settings.mm_per_pixel
    cx, cy = centre_px
    yy, xx = np.mgrid[0:n, 0:n].astype(np.float64)
    dist = np.hypot(xx - cx, yy - cy)
    out = np.zeros((n, n, 3))
    tiers = [(dist < 8, 16), ((dist >= 8) & (dist < 40), 6), (dist >= 40, 2)]
    for mask, s in tiers:
        py, px = np.nonzero(mask)
        if py.size == 0:
            continue
        grid = (np.arange(s) + 0.5) / s - 0.5
        sx, sy = np.meshgrid(grid, grid)
        sx, sy = sx.ravel(), sy.ravel()
        # The footprint offsets are a random permutation of another stratified grid, so
        # pixel area and footprint are sampled jointly without a product of the two.
        perm = rng.permutation(s * s)
        fx = sx[perm] * settings.footprint_mm / mmpp
        fy = sy[perm] * settings.footprint_mm / mmpp
        acc = np.zeros((py.size, 3))
        for j in range(s * s):
            r_px = np.hypot(px + sx[j] - cx - fx[j], py + sy[j] - cy - fy[j])
            acc += truth.camera_profile(r_px * mmpp)
        out[py, px] = acc / (s * s)
    return out


def hair_transmission(
    size_px: int, centre_px: tuple[float, float], strands: int, rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Transmission map of dark hair strands crossing the spot (not the entry point itself:
    the paper re-shot spots whose entry point a hair covered)."""
    yy, xx = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    trans = np.ones((size_px, size_px))
    for _ in range(strands):
        angle = rng.uniform(0, math.pi)
        offset = rng.uniform(6.0, 40.0) * rng.choice([-1.0, 1.0])
        width = rng.uniform(1.5, 3.0)
        nx, ny = -math.sin(angle), math.cos(angle)
        d = np.abs((xx - centre_px[0]) * nx + (yy - centre_px[1]) * ny - offset)
        cover = np.clip(1.0 - (d - width / 2), 0.0, 1.0)  # one-pixel anti-aliased edge
        trans *= 1.0 - 0.85 * cover
    return trans


def expose(
    irradiance: NDArray[np.float64], exposure_s: float, settings: CaptureSettings,
    rng: np.random.Generator,
) -> NDArray[np.float64]:
    """Sensor response: photon (Poisson) and read noise, clipping, quantisation, encoding.

    ``irradiance`` is in code units per second (1 = full scale). Returns code values in
    [0, 1] as stored in the file (sRGB-encoded for 8-bit).
    """
    electrons = np.clip(irradiance * exposure_s, 0.0, None) * settings.full_well_e
    signal = rng.poisson(np.minimum(electrons, 1e9)).astype(np.float64)
    signal += rng.normal(0.0, settings.read_noise_e, signal.shape)
    linear = np.clip(signal / settings.full_well_e, 0.0, 1.0)
    if settings.bits == 8:
        linear = np.clip(convert_colorspace(linear, CAMERA_LINEAR, CAMERA_SRGB), 0.0, 1.0)
    top = (1 << settings.bits) - 1
    return np.rint(linear * top) / top


def simulate_region(
    truth: RegionTruth, settings: CaptureSettings, out_dir: Path, rng: np.random.Generator,
) -> tuple[SimulatedRegion, list[tuple[Path, NDArray[np.float64], float]]]:
    """Render one region's brackets in memory; returns the file plan (path, code values, t)."""
    n = settings.size_px
    centre = (n / 2 + rng.uniform(-0.5, 0.5) - 0.5, n / 2 + rng.uniform(-0.5, 0.5) - 0.5)
    image = spot_image(truth, settings, centre, rng)
    if settings.hair_strands:
        image *= hair_transmission(n, centre, settings.hair_strands, rng)[..., None]
    # Scale so that the brightest pixel reaches peak_fraction of full scale in the
    # shortest exposure: the set then spans the whole profile.
    scale = settings.peak_fraction / (image.max() * min(settings.exposures_s))
    plan = []
    for i, t in enumerate(settings.exposures_s):
        code = expose(image * scale, t, settings, rng)
        plan.append((out_dir / truth.name / f"e{i}.{settings.image_format}", code, t))
    return SimulatedRegion(truth, centre), plan


def simulate_capture_set(
    truths: list[RegionTruth], out_dir: str | Path, settings: CaptureSettings | dict[str, Any],
    subject: str = "simulated", seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Write a capture set (capture.json, images) plus truth.json with the true profiles.

    ``settings`` may map region names to their own :class:`CaptureSettings` (a
    ``"default"`` entry for the rest), so one subject can mix 16-bit TIFF and 8-bit PNG.
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
                         "(bits 8 = sRGB, 16 = linear)")
    rng = np.random.default_rng(seed)
    manifest: dict[str, Any] = {"subject": subject, "mm_per_pixel": default.mm_per_pixel,
                                "camera_colorspace": default.colorspace, "regions": {}}
    truth_doc: dict[str, Any] = {"subject": subject, "seed": seed, "camera_linear": CAMERA_LINEAR,
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
            "truth": truth.to_json(), "entry_point_px": list(sim.entry_point_px),
            "settings": asdict(st),
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
