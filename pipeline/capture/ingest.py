"""Ingest stage: bracketed photographs of one lit projector pixel -> radial profiles in mm.

Park & Oh 2009, section 2: one projector pixel lights the skin, the camera shoots
several exposures, the brackets are merged into an HDR image and the profile is read
through the entry point. We read every ring around the entry point with a median over
angle (hair and follicle shadows cover a small part of a ring), and keep the paper's
single cross-section as a mode for comparison.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from pathlib import Path
from typing import Any, Literal

import numpy as np
from colour_hdri import weighting_function_Debevec1997
from numpy.typing import NDArray
from scipy.ndimage import gaussian_filter, map_coordinates, median_filter

from ..errors import InputError, SkinpipeError
from ..fileio import atomic_write_json, check_path_name
from ..imageio import (
    ACESCG,
    LoadedImage,
    check_colorspace,
    colorspace_matrix,
    convert_colorspace,
    read_image,
    write_exr,
)
from ..profile.io import write_profile_csv
from ..profile.models import (
    TailExtrapolation,
    expected_error_eq2c,
    extrapolated_tail,
    ring_areas_mm2,
)
from ..profile.types import MeasuredProfile

FloatImage = NDArray[np.float32]
ProfileMode = Literal["rings", "cross_section"]
PAPER_REGIONS = ("forehead", "lips", "chin", "cheekbone", "cheek", "nose")


@dataclass(frozen=True)
class Bracket:
    path: Path
    exposure_s: float | None


@dataclass(frozen=True)
class CaptureSet:
    """A parsed ``capture.json``: see docs/capture-format.md."""

    root: Path
    subject: str
    mm_per_pixel: float
    camera_colorspace: str
    regions: dict[str, list[Bracket]]
    sensor: SensorNoise | None = None
    """The camera's noise from the manifest's ``sensor``; None: estimated per region."""

    @property
    def files(self) -> list[Path]:
        """Every file the capture set consists of: capture.json and the brackets."""
        return [self.root / "capture.json"] + [b.path for bs in self.regions.values()
                                               for b in bs]


@dataclass(frozen=True)
class IngestOptions:
    """Ring width in pixels, fit range in mm, and the merge's trusted code-value range."""

    ring_width_px: float = 1.0
    max_radius_mm: float | None = None
    mode: ProfileMode = "rings"
    absolute: bool = False
    noise_floor: float | None = None  # code value below which a bracket is not trusted
    clip_level: float = 0.98  # code value above which a bracket is clipped


@dataclass
class RegionResult:
    region: str
    profile: MeasuredProfile
    hdr: FloatImage
    entry_point_px: tuple[float, float]
    seconds: float
    brackets: int
    unresolved_fraction: float
    warnings: list[str] = field(default_factory=list)
    noise: SensorNoise | None = None
    tail: TailExtrapolation | None = None


def read_capture_set(root: str | Path) -> CaptureSet:
    """Parse and validate CAPTURES/capture.json; every problem names the file and key."""
    root = Path(root)
    manifest = root / "capture.json"
    if not manifest.is_file():
        raise InputError("no capture.json in the capture directory", root)
    try:
        doc = json.loads(manifest.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not valid JSON: {exc}", manifest) from exc
    if not isinstance(doc, dict):
        raise InputError("must be a JSON object", manifest)
    for key in ("mm_per_pixel", "camera_colorspace", "regions"):
        if key not in doc:
            raise InputError(f"missing key {key!r}", manifest)
    mmpp = doc["mm_per_pixel"]
    if isinstance(mmpp, bool) or not isinstance(mmpp, int | float) or \
            not math.isfinite(mmpp) or not 0 < mmpp < 10:
        raise InputError(f"mm_per_pixel must be a number in (0, 10) mm, got {mmpp!r}", manifest)
    try:
        colorspace = check_colorspace(str(doc["camera_colorspace"]))
    except InputError as exc:
        raise InputError(str(exc), manifest) from exc
    regions_doc = doc["regions"]
    if not isinstance(regions_doc, dict) or not regions_doc:
        raise InputError("'regions' must be a non-empty object {name: {images: [...]}}", manifest)
    regions: dict[str, list[Bracket]] = {}
    for name, entry in regions_doc.items():
        check_path_name(name, "region", manifest)
        images = entry.get("images") if isinstance(entry, dict) else None
        if not isinstance(images, list) or not images:
            raise InputError(f"region {name!r}: 'images' must be a non-empty list", manifest)
        brackets = []
        for i, img in enumerate(images):
            if not isinstance(img, dict) or not isinstance(img.get("file"), str):
                raise InputError(f"region {name!r}, image {i}: needs a 'file' string", manifest)
            exp = img.get("exposure_s")
            if exp is not None and (isinstance(exp, bool) or not isinstance(exp, int | float)
                                    or not exp > 0 or not math.isfinite(exp)):
                raise InputError(
                    f"region {name!r}, {img['file']}: exposure_s must be > 0 s, got {exp!r}",
                    manifest)
            brackets.append(Bracket(root / img["file"], None if exp is None else float(exp)))
        regions[str(name)] = brackets
    sensor = _read_sensor(doc.get("sensor"), manifest)
    subject = doc.get("subject", root.absolute().name)
    if not isinstance(subject, str) or not subject.strip():
        raise InputError(f"'subject' must be a non-empty string, got {subject!r}", manifest)
    return CaptureSet(root, subject, float(mmpp), colorspace, regions, sensor)


def _read_sensor(doc: Any, manifest: Path) -> SensorNoise | None:
    """``"sensor": {"full_well_e": N, "read_noise_e": s}`` (electrons at full scale, read
    noise in electrons) as a :class:`SensorNoise`; absent: None."""
    if doc is None:
        return None
    if not isinstance(doc, dict) or set(doc) != {"full_well_e", "read_noise_e"}:
        raise InputError("'sensor' must be {\"full_well_e\": N, \"read_noise_e\": s}, got "
                         f"{doc!r}", manifest)
    well, read = doc["full_well_e"], doc["read_noise_e"]
    for key, v, least in (("full_well_e", well, "> 0"), ("read_noise_e", read, ">= 0")):
        number = not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)
        if not number or not (v > 0 if least == "> 0" else v >= 0):
            raise InputError(f"sensor.{key} must be a finite number {least}, got {v!r}",
                             manifest)
    return SensorNoise(1.0 / well, read / well, "manifest")


# ------------------------------------------------------------------------------- merging


def _is_scene_linear(colorspace: str) -> bool:
    """Whether OCIO's transform from ``colorspace`` to ACEScg is linear (a matrix)."""
    probe = np.array([[[0.02, 0.3, 0.7], [0.04, 0.6, 1.4]]], np.float32)
    out = convert_colorspace(probe, colorspace, ACESCG).astype(np.float64)
    return bool(np.allclose(out[0, 1], 2 * out[0, 0], rtol=1e-4, atol=1e-7))


@dataclass(frozen=True)
class SensorNoise:
    """Noise of a linear sensor in code values (1 = full scale): a pixel that records c
    has variance ``gain * c + read ** 2`` (shot noise: ``gain`` is one electron in
    code values; read noise ``read``)."""

    gain: float
    read: float
    source: str
    """"manifest", or "estimated" from the brackets themselves."""


def estimate_sensor_noise(codes: list[NDArray[Any]], exposures_s: list[float],
                          clip_level: float = 0.98) -> SensorNoise:
    """Shot and read noise from the brackets themselves (Granados et al. 2010, sec. 4):
    for consecutive exposures t1 < t2 (ratio r) the difference d = c2 - r c1 of a pixel
    unclipped in both has variance g mu2 (1 + r) + s^2 (1 + r^2), mu2 its expected code
    in the longer one; a straight line through d's robust variance (MAD) in bins of
    mu2 gives the gain g and read noise s."""
    order = np.argsort(exposures_s)
    xs, ys, ws = [], [], []
    for a, b in pairwise(order):
        r = exposures_s[b] / exposures_s[a]
        c1, c2 = codes[a].astype(np.float64), codes[b].astype(np.float64)
        ok = (c1 < clip_level) & (c2 < clip_level)
        ok &= np.all(c2 < clip_level, axis=2, keepdims=True) & \
            np.all(c1 < clip_level, axis=2, keepdims=True)
        mu2 = gaussian_filter(c2, sigma=(1.5, 1.5, 0))  # expected code, not the noisy one
        d = (c2 - r * c1)[ok]
        m = mu2[ok]
        if d.size < 200:
            continue
        edges = np.unique(np.quantile(m, np.linspace(0, 1, 21)))
        for lo, hi in pairwise(edges):
            sel = (m >= lo) & (m < hi)
            if sel.sum() < 50:
                continue
            dd = d[sel]
            mad = np.median(np.abs(dd - np.median(dd)))
            xs.append([float(np.median(m[sel])) * (1 + r), 1 + r * r])
            ys.append((1.4826 * mad) ** 2)
            ws.append(float(sel.sum()))
    if len(ys) < 3:
        raise InputError("cannot estimate the sensor's noise from these brackets (too few "
                         "unclipped pixels in consecutive exposures): give "
                         "'sensor': {'full_well_e': ..., 'read_noise_e': ...} in capture.json")
    x, y, w = np.asarray(xs), np.asarray(ys), np.sqrt(np.asarray(ws))
    (gain, read2), *_ = np.linalg.lstsq(x * w[:, None], y * w, rcond=None)
    return SensorNoise(max(float(gain), 1e-12), math.sqrt(max(float(read2), 1e-16)),
                       "estimated")


@dataclass(frozen=True)
class MergedExposures:
    """A merge's result: the ACEScg image (radiance per second), the pixels no bracket
    resolved, and for a noise-optimal merge its per-pixel variance (ACEScg, per
    second^2; inf where unresolved) and the noise model it used."""

    hdr: FloatImage
    unresolved: NDArray[np.bool_]
    variance: NDArray[np.float64] | None = None
    noise: SensorNoise | None = None


def merge_exposures(
    images: list[LoadedImage],
    exposures_s: list[float],
    colorspace: str,
    noise_floor: float | None = None,
    clip_level: float = 0.98,
    noise: SensorNoise | None = None,
) -> MergedExposures:
    """Merge exposures into one scene-linear ACEScg HDR image (radiance per second).

    Linear integer captures: each unclipped bracket's radiance c / t weighted by its
    inverse variance t^2 / (g mu t + s^2) from the sensor's noise (``noise``, else
    estimated from the brackets, :func:`estimate_sensor_noise`), evaluated on a smoothed
    estimate mu of the radiance, never on the pixel's own noisy value (Granados et al.
    2010, "Optimal HDR reconstruction with linear digital cameras"; Hasinoff et al.
    2010): a weight that follows the noisy value picks the short brackets' upward noise
    in the dark and biases the flux. The only hard cut is saturation; a pixel clipped
    in any channel is not used from that bracket. Merged in the camera's space, then
    converted; the merge's variance is 1 / the sum of the weights, carried through the
    colour matrix with independent channels (var' = (M o M) var). Non-linear (8-bit
    sRGB) captures keep Debevec & Malik 1997's hat weights (colour-hdri) times t.
    """
    if all(not img.is_float for img in images) and _is_scene_linear(colorspace):
        return _merge_noise_optimal(images, exposures_s, colorspace, clip_level, noise)
    return MergedExposures(*_merge_hat(images, exposures_s, colorspace, noise_floor,
                                       clip_level))


def _merge_noise_optimal(images: list[LoadedImage], exposures_s: list[float],
                         colorspace: str, clip_level: float, noise: SensorNoise | None
                         ) -> MergedExposures:
    codes = [img.pixels.astype(np.float64) for img in images]
    t = np.asarray(exposures_s, np.float64)
    single = len(codes) == 1  # one bracket: its weights cancel, no noise model is needed
    if noise is None and not single:
        noise = estimate_sensor_noise(codes, exposures_s, clip_level)
    model = noise or SensorNoise(1.0, 1.0, "not needed (one bracket)")
    valid = [~np.any(c >= clip_level, axis=2, keepdims=True) for c in codes]
    # first estimate: the longest unclipped bracket at each pixel
    mu = np.zeros_like(codes[0])
    for i in np.argsort(t):
        mu = np.where(valid[i], codes[i] / t[i], mu)
    for _ in range(2):
        weights = _inverse_variance_weights(mu, t, valid, model)
        num = sum(w * c / ti for w, c, ti in zip(weights, codes, t, strict=True))
        den = sum(weights)
        resolved = den > 0
        mu = np.where(resolved, num / np.where(resolved, den, 1.0), mu)
    shortest = int(np.argmin(t))
    mu = np.where(resolved, mu, codes[shortest] / t[shortest])  # clipped everywhere
    hdr = convert_colorspace(mu.astype(np.float32), colorspace, ACESCG).astype(np.float32)
    variance = None
    if not single:
        m = colorspace_matrix(colorspace, ACESCG)
        with np.errstate(divide="ignore"):
            variance = np.where(resolved, 1.0 / np.where(resolved, den, 1.0), np.inf) @ \
                (m * m).T
    return MergedExposures(hdr, ~np.all(resolved, axis=2), variance, noise)


def _inverse_variance_weights(mu: NDArray[np.float64], t: NDArray[np.float64],
                              valid: list[NDArray[np.bool_]], noise: SensorNoise
                              ) -> list[NDArray[np.float64]]:
    """Each bracket's weight t^2 / (g mu t + s^2) (zero where clipped), the inverse
    variance of its radiance estimate c / t, on a smoothed radiance estimate ``mu``
    (camera space, code values per second)."""
    smooth = gaussian_filter(np.maximum(mu, 0.0), sigma=(1.0, 1.0, 0))
    return [ok * ti * ti / (noise.gain * smooth * ti + noise.read ** 2)
            for ti, ok in zip(t, valid, strict=True)]


def _merge_hat(images: list[LoadedImage], exposures_s: list[float], colorspace: str,
               noise_floor: float | None, clip_level: float
               ) -> tuple[FloatImage, NDArray[np.bool_]]:
    """Debevec & Malik 1997 weighting (colour-hdri's hat function, zero at the noise
    floor and at clipping) times the exposure time (Robertson et al. 2003)."""
    floor = noise_floor if noise_floor is not None else (2.0 / 255.0 if images[0].bits == 8
                                                         else 2e-4)
    num = np.zeros(images[0].pixels.shape, dtype=np.float64)
    den = np.zeros_like(num)
    radiance = []  # per bracket, ACEScg per second
    for img, t in zip(images, exposures_s, strict=True):
        code = img.pixels
        if img.is_float:
            weight = np.ones_like(code, dtype=np.float64)
        else:
            weight = weighting_function_Debevec1997(code, domain_l=floor, domain_h=clip_level)
            clipped = np.any(code >= clip_level, axis=2, keepdims=True)
            weight = np.where(clipped, 0.0, weight)
        radiance.append(convert_colorspace(code, colorspace, ACESCG).astype(np.float64) / t)
        num += weight * t * radiance[-1]
        den += weight * t
    resolved = den > 0
    # Unresolved pixels: below the floor in every bracket -> the longest exposure's value;
    # clipped in every bracket -> the shortest exposure's (a lower bound).
    longest = int(np.argmax(exposures_s))
    shortest = int(np.argmin(exposures_s))
    bright = np.any(images[shortest].pixels >= clip_level, axis=2, keepdims=True)
    fallback = np.where(bright, radiance[shortest], radiance[longest])
    hdr = np.where(resolved, num / np.where(resolved, den, 1.0), fallback)
    return hdr.astype(np.float32), ~np.all(resolved, axis=2)


# ---------------------------------------------------------------------- entry and profile


def _weighted_centroid(hdr: FloatImage, window_px: float) -> tuple[float, float]:
    """Iteratively re-weighted centroid under a Gaussian window, background subtracted.

    Starts at the brightest pixel after a 3x3 median (which ignores hot pixels). For a
    radially symmetric spot the true centre is the fixed point, whatever the pixel grid.
    """
    lum = hdr.sum(axis=2).astype(np.float64)
    smooth = median_filter(lum, size=3, mode="nearest")
    y0, x0 = np.unravel_index(int(np.argmax(smooth)), smooth.shape)
    half = math.ceil(4 * window_px)
    ys = slice(max(0, y0 - half), min(lum.shape[0], y0 + half + 1))
    xs = slice(max(0, x0 - half), min(lum.shape[1], x0 + half + 1))
    patch = lum[ys, xs]
    background = float(np.median(lum))
    mass = np.maximum(patch - background, 0.0)
    if not mass.sum() > 0:
        raise InputError("no lit spot found: the merged image is flat")
    yy, xx = np.mgrid[ys, xs].astype(np.float64)
    cx, cy = float(x0), float(y0)
    for _ in range(50):
        w = mass * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * window_px**2))
        nx, ny = float((w * xx).sum() / w.sum()), float((w * yy).sum() / w.sum())
        done = abs(nx - cx) + abs(ny - cy) < 1e-4
        cx, cy = nx, ny
        if done:
            break
    return cx, cy


def find_entry_point(hdr: FloatImage, radius_px: int | None = None) -> tuple[float, float]:
    """Sub-pixel entry point (x, y) in pixel coordinates (pixel centres at integers).

    The centre of point symmetry of the log-intensity: the c minimising
    sum |f(c + d) - f(c - d)| over offsets d within ``radius_px``, f interpolated
    (cubic). ``radius_px`` defaults to where the spot falls to 30% of its peak (a
    flat-topped dipole spot needs a wide window). The sum leaves out the half most
    asymmetric pairs: a dark hair strand breaks the symmetry on a few pixels whatever c
    is, and must not pull the estimate as it pulls a centroid. Starts from a tight
    centroid around the brightest pixel.
    """
    from scipy.ndimage import spline_filter  # lazy: 0.25 s to import
    from scipy.optimize import minimize  # lazy: 0.50 s to import

    start = _weighted_centroid(hdr, window_px=1.5)
    lum = hdr.sum(axis=2).astype(np.float64)
    peak = float(lum.max())
    f = np.log(np.maximum(lum, 1e-6 * peak))
    if radius_px is None:
        yy0, xx0 = np.indices(lum.shape)
        ring = np.hypot(xx0 - start[0], yy0 - start[1]).astype(np.int64).ravel()
        mean = np.bincount(ring, lum.ravel()) / np.maximum(np.bincount(ring), 1)
        below = np.flatnonzero(mean < 0.3 * mean[0])
        radius_px = int(np.clip(below[0] if below.size else 12, 8, 60))
    coeffs = spline_filter(f, order=3)
    yy, xx = np.mgrid[-radius_px : radius_px + 1, -radius_px : radius_px + 1]
    half = (yy > 0) | ((yy == 0) & (xx > 0))
    inside = half & (xx**2 + yy**2 <= radius_px**2)
    dx, dy = xx[inside].astype(np.float64), yy[inside].astype(np.float64)
    keep = int(0.5 * dx.size)

    def asymmetry(c: NDArray[np.float64]) -> float:
        a = map_coordinates(coeffs, [c[1] + dy, c[0] + dx], order=3, prefilter=False,
                            mode="nearest")
        b = map_coordinates(coeffs, [c[1] - dy, c[0] - dx], order=3, prefilter=False,
                            mode="nearest")
        diff = np.abs(a - b)
        # trimmed: the most asymmetric half are hair or follicles, whatever c is
        return float(np.partition(diff, keep)[:keep].sum())

    res = minimize(asymmetry, np.array(start), method="Nelder-Mead",
                   options={"xatol": 1e-3, "fatol": 1e-9, "initial_simplex":
                            np.array(start) + np.array([[0, 0], [0.5, 0], [0, 0.5]])})
    cx, cy = float(res.x[0]), float(res.x[1])
    if np.hypot(cx - start[0], cy - start[1]) > max(3.0, 0.25 * radius_px):
        return start  # the symmetry search wandered off: keep the centroid (+-1 px)
    return cx, cy


def radial_profile(
    hdr: FloatImage,
    centre_px: tuple[float, float],
    mm_per_pixel: float,
    ring_width_px: float = 1.0,
    max_radius_mm: float | None = None,
    mode: ProfileMode = "rings",
    variance: NDArray[np.float64] | None = None,
    exclude: NDArray[np.bool_] | None = None,
) -> MeasuredProfile:
    """The radial profile around ``centre_px`` with per-sample standard errors.

    ``rings``: the median over each ring of width ``ring_width_px`` (robust to hair and
    follicle shadows), at the ring's median pixel distance; standard error from the
    median absolute deviation (1.2533 * 1.4826 MAD / sqrt(n)), and no smaller than what
    the sensor's noise alone gives (``variance``, per pixel: sqrt(pi/2 sum var) / n, the
    median's efficiency); without ``variance``, no smaller than 1% of the value. Pixels
    in ``exclude`` (hair, :func:`hair_mask`) are left out of the rings.
    ``cross_section``: Park & Oh's single horizontal line through the entry point,
    bilinearly sampled, left and right sides averaged; their half-difference as error.
    """
    h, w, _ = hdr.shape
    cx, cy = centre_px
    limit_px = min(cx, cy, w - 1 - cx, h - 1 - cy)
    if max_radius_mm is not None:
        limit_px = min(limit_px, max_radius_mm / mm_per_pixel)
    if limit_px < 4 * ring_width_px:
        raise InputError(f"the entry point ({cx:.1f}, {cy:.1f}) is too close to the image border")
    if mode == "cross_section":
        radii = np.arange(0.0, limit_px, ring_width_px)
        left = np.stack([map_coordinates(hdr[..., c], [np.full_like(radii, cy), cx - radii],
                                         order=1) for c in range(3)], axis=1)
        right = np.stack([map_coordinates(hdr[..., c], [np.full_like(radii, cy), cx + radii],
                                          order=1) for c in range(3)], axis=1)
        values = 0.5 * (left + right)
        stderr = 0.5 * np.abs(left - right)
        return MeasuredProfile(radii * mm_per_pixel, values, _floor_std(stderr, values))
    yy, xx = np.mgrid[0:h, 0:w]
    dist = np.hypot(xx - cx, yy - cy).ravel()
    ring = np.floor(dist / ring_width_px + 0.5).astype(np.int64)
    n_rings = int(limit_px / ring_width_px)
    keep = ring < n_rings
    if exclude is not None:
        keep &= ~exclude.ravel()
    ring, dist = ring[keep], dist[keep]
    pix = hdr.reshape(-1, 3)[keep].astype(np.float64)
    var = None if variance is None else variance.reshape(-1, 3)[keep]
    order = np.argsort(ring, kind="stable")
    ring, dist, pix = ring[order], dist[order], pix[order]
    var = None if var is None else var[order]
    bounds = np.searchsorted(ring, np.arange(n_rings + 1))
    radii = np.empty(n_rings)
    values = np.empty((n_rings, 3))
    stderr = np.empty((n_rings, 3))
    for i in range(n_rings):
        a, b = bounds[i], bounds[i + 1]
        if b <= a:
            radii[i] = i * ring_width_px
            values[i] = np.nan
            stderr[i] = np.nan
            continue
        seg = pix[a:b]
        med = np.median(seg, axis=0)
        mad = np.median(np.abs(seg - med), axis=0)
        radii[i] = float(np.median(dist[a:b]))
        values[i] = med
        stderr[i] = 1.2533 * 1.4826 * mad / math.sqrt(b - a)
        if var is not None:
            stderr[i] = np.maximum(stderr[i], np.sqrt(0.5 * math.pi * var[a:b].sum(axis=0))
                                   / (b - a))
    ok = np.isfinite(values).all(axis=1)
    if var is not None:
        ok &= np.isfinite(stderr).all(axis=1)
        return MeasuredProfile(radii[ok] * mm_per_pixel, values[ok], stderr[ok])
    return MeasuredProfile(radii[ok] * mm_per_pixel, values[ok],
                           _floor_std(stderr[ok], values[ok]))


HAIR_RATIO = 0.6
"""A pixel darker than this share of the radial model at its radius (3 x 3 median of
the ratio: a strand is 1.5-3 px wide) is hair; the paper's strands pass 10-50% of the
light."""
HAIR_CORE_PX = 3.0
HAIR_CORE_LIMIT = 0.5
"""A capture whose entry point is hair, or whose core (within HAIR_CORE_PX of it) is
more than this share hair, is refused: the paper re-shot such spots. A strand passing
2-4 px beside the entry point covers 15-40% of the core and is masked."""


def hair_mask(hdr: FloatImage, centre_px: tuple[float, float], profile_px: MeasuredProfile,
              variance: NDArray[np.float64] | None = None) -> NDArray[np.bool_]:
    """Hair strands as dark outliers against the radial model: pixels whose luminance,
    3 x 3 median filtered, is below HAIR_RATIO of the profile at their radius, where the
    model stands 10 noise sigmas above zero (or, without a noise model, above 1% of its
    peak), grown by one pixel for the strands' soft edges. ``profile_px``: radii in px."""
    h, w, _ = hdr.shape
    yy, xx = np.mgrid[0:h, 0:w]
    r = np.hypot(xx - centre_px[0], yy - centre_px[1])
    lum = hdr.astype(np.float64).sum(axis=2)
    model = np.interp(r, profile_px.radius_mm, profile_px.values.sum(axis=1), right=np.nan)
    ratio = median_filter(lum / np.where(model > 0, model, np.nan), size=3, mode="nearest")
    if variance is not None:
        trusted = model > 10.0 * np.sqrt(np.where(np.isfinite(variance), variance, np.inf)
                                         .sum(axis=2))
    else:
        trusted = model > 0.01 * np.nanmax(model)
    dark = trusted & (ratio < HAIR_RATIO)
    grown = dark.copy()
    grown[1:] |= dark[:-1]
    grown[:-1] |= dark[1:]
    grown[:, 1:] |= dark[:, :-1]
    grown[:, :-1] |= dark[:, 1:]
    return grown


def hair_over_core(hair: NDArray[np.bool_], centre_px: tuple[float, float]
                   ) -> tuple[float, bool]:
    """The share of the core (within HAIR_CORE_PX of the entry point) that ``hair``
    covers, and whether it covers the entry point's own pixel."""
    yy, xx = np.mgrid[0:hair.shape[0], 0:hair.shape[1]]
    core = np.hypot(xx - centre_px[0], yy - centre_px[1]) <= HAIR_CORE_PX
    return float(hair[core].mean()), bool(hair[round(centre_px[1]), round(centre_px[0])])


def _floor_std(stderr: NDArray[np.float64], values: NDArray[np.float64]) -> NDArray[np.float64]:
    # A ring of one or two pixels has no spread to measure: assume 1% of the value.
    floor = 0.01 * np.abs(values) + 1e-12 * np.abs(values).max()
    return np.maximum(stderr, floor)


TAIL_WARN_FRACTION = 0.25
"""A channel with more of its light extrapolated beyond the image than this is noted:
the field of view is too small for it."""


def normalise_profile(profile: MeasuredProfile
                      ) -> tuple[MeasuredProfile, NDArray[np.float64], TailExtrapolation]:
    """Scale each channel so that 2 pi int p r dr = 1 over the whole plane: the measured
    disk (ring areas) plus the tail beyond it, extrapolated from the measured tail
    (:func:`~pipeline.profile.models.extrapolated_tail`). Returns the profile, each
    channel's flux and the tail."""
    r = profile.radius_mm
    disk = (profile.values * ring_areas_mm2(r)[:, None]).sum(axis=0)
    if not np.all(disk > 0):
        raise InputError(f"a channel has no light in the spot (flux {disk.tolist()})")
    tail = extrapolated_tail(r, profile.values, profile.stddev)
    flux = disk + tail.flux_beyond
    std = None if profile.stddev is None else profile.stddev / flux
    return (MeasuredProfile(r, profile.values / flux, std, profile.name, profile.source),
            flux, tail)


# ------------------------------------------------------------------------------ the stage


def _load_region(captures: CaptureSet, region: str) -> tuple[list[LoadedImage], list[float]]:
    images = [read_image(b.path) for b in captures.regions[region]]
    exposures: list[float] = []
    for b, img in zip(captures.regions[region], images, strict=True):
        t = b.exposure_s if b.exposure_s is not None else img.exposure_s
        if t is None:
            raise InputError("no exposure time: neither capture.json nor the file's EXIF "
                             "ExposureTime gives one", b.path)
        exposures.append(t)
    shapes = {img.pixels.shape for img in images}
    if len(shapes) > 1:
        detail = ", ".join(f"{i.path.name} {i.pixels.shape[1]}x{i.pixels.shape[0]}"
                           for i in images)
        raise InputError(f"region {region!r}: brackets differ in size ({detail})",
                         images[0].path.parent)
    floor = 2.0 / 255.0 if images[0].bits == 8 else 2e-4
    if all(not i.is_float and i.pixels.max() <= floor for i in images):
        raise InputError(f"region {region!r}: every bracket is black (max code value "
                         f"<= {floor:.4f}): no light reached the camera", images[0].path.parent)
    return images, exposures


def ingest_region(
    captures: CaptureSet, region: str, options: IngestOptions | None = None,
    warn: Callable[[str], None] | None = None,
) -> RegionResult:
    """Merge one region's brackets and extract its radial profile (ACEScg, mm)."""
    options = options or IngestOptions()
    notes: list[str] = []

    def note(msg: str) -> None:
        notes.append(msg)
        if warn is not None:
            warn(f"{region}: {msg}")

    start = time.perf_counter()
    images, exposures = _load_region(captures, region)
    clip = options.clip_level
    if not any(img.is_float for img in images):
        if all(np.any(img.pixels >= clip) and _centre_clipped(img, clip) for img in images):
            raise InputError(f"region {region!r}: every bracket is clipped at the entry point; "
                             "add a shorter exposure", images[0].path.parent)
    if len(images) == 1:
        if not images[0].is_float and np.any(images[0].pixels >= clip):
            raise InputError(f"region {region!r}: a single bracket that is clipped cannot be "
                             "merged; shoot several exposures", images[0].path)
        note("one bracket only: the profile's dynamic range is that of one exposure")
    merged = merge_exposures(images, exposures, captures.camera_colorspace,
                             options.noise_floor, clip, captures.sensor)
    hdr, unresolved, variance = merged.hdr, merged.unresolved, merged.variance
    centre = find_entry_point(hdr)
    rings = variance if options.mode == "rings" else None
    profile = radial_profile(hdr, centre, captures.mm_per_pixel, options.ring_width_px,
                             options.max_radius_mm, options.mode, rings)
    if options.mode == "rings":
        hair = hair_mask(hdr, centre, MeasuredProfile(profile.radius_mm / captures.mm_per_pixel,
                                                      profile.values), variance)
        covered, on_entry = hair_over_core(hair, centre)
        if covered > HAIR_CORE_LIMIT or on_entry:
            raise SkinpipeError(
                f"region {region!r}: hair covers {covered:.0%} of the core (within "
                f"{HAIR_CORE_PX:g} px of the entry point): too little clean skin to measure "
                "the narrow scattering; re-shoot this spot")
        if hair.any():
            note(f"{int(hair.sum())} pixels of hair masked before the ring statistics")
            profile = radial_profile(hdr, centre, captures.mm_per_pixel,
                                     options.ring_width_px, options.max_radius_mm,
                                     options.mode, rings, hair)
    profile = MeasuredProfile(profile.radius_mm, profile.values, profile.stddev, region,
                              captures.root / "capture.json")
    tail = None
    if not options.absolute:
        profile, _, tail = normalise_profile(profile)
        wide = [f"{c} {f:.0%}" for c, f in zip("RGB", tail.fraction_beyond, strict=True)
                if f > TAIL_WARN_FRACTION]
        if wide:
            note(f"light beyond the image, extrapolated: {', '.join(wide)} of the channel's "
                 "flux; a wider field of view would measure it")
    return RegionResult(region, profile, hdr, centre, time.perf_counter() - start, len(images),
                        float(unresolved.mean()), notes, merged.noise, tail)


def _centre_clipped(img: LoadedImage, clip: float) -> bool:
    lum = img.pixels.sum(axis=2)
    y, x = np.unravel_index(int(np.argmax(lum)), lum.shape)
    return bool(np.any(img.pixels[y, x] >= clip))


def ingest_capture_set(
    root: str | Path, out_dir: str | Path, options: IngestOptions | None = None,
    progress: Callable[[str], None] | None = None, regions: list[str] | None = None,
) -> dict[str, Any]:
    """Ingest every region, then write ``<region>.csv``, ``<region>.exr`` and ``ingest.json``.

    All regions are processed before anything is written: bad input anywhere writes
    nothing. Each file is written to a temporary name and renamed.
    """
    options = options or IngestOptions()
    captures = read_capture_set(root)
    names = regions or list(captures.regions)
    unknown = [n for n in names if n not in captures.regions]
    if unknown:
        raise InputError(f"no such region(s) {unknown}; the capture has {list(captures.regions)}",
                         captures.root / "capture.json")
    results = []
    for i, name in enumerate(names, start=1):
        res = ingest_region(captures, name, options, warn=progress)
        results.append(res)
        if progress is not None:
            progress(f"[{i}/{len(names)}] {name}: {res.brackets} brackets, entry point "
                     f"({res.entry_point_px[0]:.2f}, {res.entry_point_px[1]:.2f}) px, "
                     f"{res.profile.radius_mm.size} samples to {res.profile.radius_mm[-1]:.2f} "
                     f"mm, {res.seconds:.2f} s")
    out = Path(out_dir)
    report: dict[str, Any] = {"stage": "ingest", "subject": captures.subject,
                              "camera_colorspace": captures.camera_colorspace,
                              "colorspace": ACESCG, "mm_per_pixel": captures.mm_per_pixel,
                              "options": options.__dict__, "regions": {}}
    for res in results:
        csv_path = write_profile_csv(out / f"{res.region}.csv", res.profile)
        exr_path = write_exr(out / f"{res.region}.exr", res.hdr, ACESCG, {
            "skinpipe:entry_point_px": f"{res.entry_point_px[0]:.4f} {res.entry_point_px[1]:.4f}",
            "skinpipe:mm_per_pixel": float(captures.mm_per_pixel),
            "skinpipe:subject": captures.subject,
        })
        report["regions"][res.region] = {
            "csv": str(csv_path), "exr": str(exr_path), "seconds": res.seconds,
            "brackets": res.brackets, "entry_point_px": list(res.entry_point_px),
            "samples": int(res.profile.radius_mm.size),
            "max_radius_mm": float(res.profile.radius_mm[-1]),
            "unresolved_pixel_fraction": res.unresolved_fraction, "warnings": res.warnings,
            # the shape's error from noise and ring statistics; the scale's uncertainty
            # (the tail beyond the image) is tail_beyond_image's
            "expected_error_eq2c": None if res.profile.stddev is None else
            expected_error_eq2c(res.profile.radius_mm, res.profile.values,
                                res.profile.stddev).tolist(),
            "tail_beyond_image": None if res.tail is None else {
                "model": list(res.tail.model),
                "fraction_of_flux": res.tail.fraction_beyond.tolist(),
                "scale_uncertainty": res.tail.scale_uncertainty.tolist()},
            "sensor_noise": None if res.noise is None else {
                "shot_code_per_electron": res.noise.gain, "read_noise_code": res.noise.read,
                "source": res.noise.source},
        }
    atomic_write_json(out / "ingest.json", report)
    return report
